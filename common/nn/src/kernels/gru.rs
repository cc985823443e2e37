//! DreamerV3's GRU update from its normalised gates.

use super::*;

#[cfg(any(test, feature = "oracle"))]
struct GruGates;

/// The gate values of one element: `(r, c, u)` with `c = tanh(r ĉ)` and `u = σ(û − 1)`.
#[inline(always)]
fn gates(pr: f32, pc: f32, pu: f32) -> (f32, f32, f32) {
    let r = sigmoid(pr);
    (r, tanh(r * pc), sigmoid(pu - 1.0))
}

vectorised! {
    /// `out` (whole rows of `size`) ← the GRU update of the gate rows `p` and states `h`.
    pub(crate) fn gru_rows(p: &[f32], h: &[f32], out: &mut [f32], size: usize) {
        let rows = p.chunks_exact(3 * size).zip(h.chunks_exact(size));
        for ((pr, hr), o) in rows.zip(out.chunks_exact_mut(size)) {
            // exact-length slices: the loop runs without bounds checks, in vector lanes
            let (pr, rest) = pr.split_at(size);
            let (pc, pu) = rest.split_at(size);
            for ((o, &h), ((&r, &c), &u)) in o.iter_mut().zip(hr).zip(pr.iter().zip(pc).zip(pu)) {
                let (_, c, u) = gates(r, c, u);
                *o = u * c + (1.0 - u) * h;
            }
        }
    }
}

vectorised! {
    /// The backward pass of [`gru_rows`] over the rows of `dp` (`3 size` each) and `dh`.
    pub(crate) fn gru_rows_bwd(p: &[f32], h: &[f32], g: &[f32], dp: &mut [f32], dh: &mut [f32], size: usize) {
        let rows = p.chunks_exact(3 * size).zip(h.chunks_exact(size)).zip(g.chunks_exact(size));
        let grads = dp.chunks_exact_mut(3 * size).zip(dh.chunks_exact_mut(size));
        for (((pr, hr), gr), (dpr, dhr)) in rows.zip(grads) {
            let (pr, rest) = pr.split_at(size);
            let (pc, pu) = rest.split_at(size);
            let (dr, rest) = dpr.split_at_mut(size);
            let (dc, du) = rest.split_at_mut(size);
            let inputs = pr.iter().zip(pc).zip(pu).zip(hr.iter().zip(gr));
            let outputs = dr.iter_mut().zip(dc.iter_mut()).zip(du.iter_mut()).zip(dhr.iter_mut());
            for ((((&pr, &pc), &pu), (&h, &gj)), (((dr, dc), du), dh)) in inputs.zip(outputs) {
                let (rg, c, u) = gates(pr, pc, pu);
                let dpre_c = gj * u * (1.0 - c * c);
                *dr = dpre_c * pc * rg * (1.0 - rg);
                *dc = dpre_c * rg;
                *du = gj * (c - h) * u * (1.0 - u);
                *dh = gj * (1.0 - u);
            }
        }
    }
}

#[cfg(any(test, feature = "oracle"))]
impl CustomOp2 for GruGates {
    fn name(&self) -> &'static str {
        "ctxrace-gru-gates"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (p, h) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        let (rows, size) = l2.shape().dims2()?;
        if p.len() != 3 * rows * size {
            bail!(
                "gru_gates: gates {:?} for a state {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let mut out = vec![0f32; h.len()];
        gru_rows(p, h, &mut out, size);
        Ok((CpuStorage::F32(out), l2.shape().clone()))
    }

    fn bwd(
        &self,
        parts: &Tensor,
        h: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (rows, size) = dims2(h)?;
        let (dp, dh) = read(parts, |p| {
            read(h, |hv| {
                read(grad, |g| {
                    let mut dp = vec![0f32; 3 * rows * size];
                    let mut dh = vec![0f32; rows * size];
                    gru_rows_bwd(p, hv, g, &mut dp, &mut dh, size);
                    Ok((dp, dh))
                })
            })
        })?;
        Ok((
            wants_grad(parts)
                .then(|| Tensor::from_vec(dp, parts.shape(), parts.device()))
                .transpose()?,
            wants_grad(h)
                .then(|| Tensor::from_vec(dh, h.shape(), h.device()))
                .transpose()?,
        ))
    }
}

/// DreamerV3's GRU update `σ(u − 1) tanh(σ(r) ĉ) + (1 − σ(u − 1)) h` from gates `[N, 3S]`
/// (`[r, ĉ, u]`, already normalised) and the state `h` `[N, S]`.
#[cfg(any(test, feature = "oracle"))]
pub fn gru_gates(parts: &Tensor, h: &Tensor) -> Result<Tensor> {
    parts.contiguous()?.apply_op2(&h.contiguous()?, GruGates)
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;

    #[test]
    fn gru_gates_match_the_composed_cell() {
        let (p, h) = (var(&[4, 9], 10), var(&[4, 3], 11));
        let n = 3;
        let reset = candle_nn::ops::sigmoid(&p.narrow(1, 0, n).unwrap()).unwrap();
        let cand = reset
            .mul(&p.narrow(1, n, n).unwrap())
            .unwrap()
            .tanh()
            .unwrap();
        let update =
            candle_nn::ops::sigmoid(&(p.narrow(1, 2 * n, n).unwrap() - 1.0).unwrap()).unwrap();
        let composed =
            (update.mul(&cand).unwrap() + (1.0 - &update).unwrap().mul(&h).unwrap()).unwrap();
        same(gru_gates(&p, &h).unwrap(), composed, &[&p, &h], 1e-5);
    }
}
