//! `LayerNorm` then SiLU or the identity, in one pass per row forward and one backward.

use super::*;

/// The activation after a [`norm_act`] normalisation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormAct {
    /// `y`.
    Identity,
    /// `y σ(y)`.
    Silu,
}

impl NormAct {
    /// `(act(y), act'(y))`.
    #[inline(always)]
    fn eval(self, y: f32) -> (f32, f32) {
        match self {
            NormAct::Identity => (y, 1.0),
            NormAct::Silu => {
                let s = sigmoid(y);
                (y * s, s * y.mul_add(1.0 - s, 1.0))
            }
        }
    }
}

struct NormActOp {
    eps: f32,
    act: NormAct,
}

/// Mean and `1/√(σ² + ε)` of a row.
#[inline(always)]
fn row_moments(x: &[f32], eps: f32) -> (f32, f32) {
    let n = x.len() as f32;
    let mean = lane_sum(x, x, |v, _| v) / n;
    let var = lane_sum(x, x, |v, _| (v - mean) * (v - mean)) / n;
    (mean, 1.0 / (var + eps).sqrt())
}

vectorised! {
    /// `act(LayerNorm(x))` of the whole rows (of `gain.len()`) of `x`, each value written
    /// once into the new buffer (never zeroed first).
    pub(super) fn norm_act_rows(x: &[f32], gain: &[f32], bias: &[f32], eps: f32, act: NormAct) -> Vec<f32> {
        let d = gain.len();
        let bias = &bias[..d];
        if d == 0 {
            return Vec::new();
        }
        let rows = x.len() / d;
        let mut out = Vec::with_capacity(rows * d);
        // exact-length rows: the loops below run without bounds checks, in vector lanes; they
        // write here rather than through `Vec::extend`, which is not inlined into this
        // function's AVX-512 and AVX2 copies and would run in baseline lanes
        for (xr, o) in x.chunks_exact(d).zip(out.spare_capacity_mut().chunks_exact_mut(d)) {
            let (mean, rstd) = row_moments(xr, eps);
            let lanes = o.iter_mut().zip(xr).zip(gain.iter().zip(bias));
            match act {
                NormAct::Identity => {
                    for ((o, &x), (&g, &b)) in lanes {
                        o.write(((x - mean) * rstd).mul_add(g, b));
                    }
                }
                NormAct::Silu => {
                    for ((o, &x), (&g, &b)) in lanes {
                        o.write(NormAct::Silu.eval(((x - mean) * rstd).mul_add(g, b)).0);
                    }
                }
            }
        }
        // SAFETY: the loop wrote all `d` values of each of the `rows` rows
        unsafe { out.set_len(rows * d) };
        out
    }
}

vectorised! {
    /// The backward pass of [`norm_act_rows`] over the whole rows of `x` and `dy`: `dx`
    /// (each value written once), and `dgb = [dγ, dβ]` accumulated.
    pub(super) fn norm_act_rows_bwd(
        x: &[f32],
        gain: &[f32],
        bias: &[f32],
        dy: &[f32],
        dgb: &mut [f32],
        eps: f32,
        act: NormAct,
    ) -> Vec<f32> {
        let d = gain.len();
        let bias = &bias[..d];
        let (dgain, dbias) = dgb.split_at_mut(d);
        let dbias = &mut dbias[..d];
        if d == 0 {
            return Vec::new();
        }
        let mut xh = vec![0f32; d];
        let mut dxh = vec![0f32; d];
        let rows = (x.len() / d).min(dy.len() / d);
        let mut dx = Vec::with_capacity(rows * d);
        let out_rows = dx.spare_capacity_mut().chunks_exact_mut(d);
        for ((xr, dyr), dxr) in x.chunks_exact(d).zip(dy.chunks_exact(d)).zip(out_rows) {
            let (mean, rstd) = row_moments(xr, eps);
            for (h, &x) in xh.iter_mut().zip(xr) {
                *h = (x - mean) * rstd;
            }
            // dxh ← the gradient at the activation's input
            match act {
                NormAct::Identity => dxh.copy_from_slice(dyr),
                NormAct::Silu => {
                    let lanes = dxh.iter_mut().zip(dyr).zip(xh.iter().zip(gain.iter().zip(bias)));
                    for ((o, &dy), (&h, (&g, &b))) in lanes {
                        *o = dy * NormAct::Silu.eval(h.mul_add(g, b)).1;
                    }
                }
            }
            let lanes = dxh.iter_mut().zip(&xh).zip(gain.iter());
            for (((o, &h), &g), (dg, db)) in lanes.zip(dgain.iter_mut().zip(dbias.iter_mut())) {
                *dg = o.mul_add(h, *dg);
                *db += *o;
                *o *= g;
            }
            let m1 = lane_sum(&dxh, &dxh, |v, _| v) / d as f32;
            let m2 = lane_sum(&dxh, &xh, |v, w| v * w) / d as f32;
            for ((o, &g), &h) in dxr.iter_mut().zip(&dxh).zip(&xh) {
                o.write(rstd * (-h).mul_add(m2, g - m1));
            }
        }
        // SAFETY: the loop wrote all `d` values of each of the `rows` rows
        unsafe { dx.set_len(rows * d) };
        dx
    }
}

impl CustomOp3 for NormActOp {
    fn name(&self) -> &'static str {
        "ctxrace-norm-act"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (x, g, b) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?, cpu_slice(s3, l3)?);
        let d = g.len();
        if d == 0 || x.len() % d != 0 || b.len() != d {
            bail!("norm_act: input {:?} for a gain of {d}", l1.shape());
        }
        let out = norm_act_rows(x, g, b, self.eps, self.act);
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gain: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = gain.elem_count();
        let want_params = wants_grad(gain) || wants_grad(bias);
        let (dx, sums) = read(x, |x| {
            read(gain, |g| {
                read(bias, |b| {
                    read(grad, |dy| {
                        let mut dgb = vec![0f32; 2 * d];
                        let dx = norm_act_rows_bwd(x, g, b, dy, &mut dgb, self.eps, self.act);
                        Ok((dx, dgb))
                    })
                })
            })
        })?;
        let dx = wants_grad(x)
            .then(|| Tensor::from_vec(dx, x.shape(), x.device()))
            .transpose()?;
        if !want_params {
            return Ok((dx, None, None));
        }
        let dg = Tensor::from_slice(&sums[..d], d, x.device())?;
        let db = Tensor::from_slice(&sums[d..], d, x.device())?;
        Ok((
            dx,
            wants_grad(gain).then_some(dg),
            wants_grad(bias).then_some(db),
        ))
    }
}

/// `act(γ (x − μ)/√(σ² + ε) + β)` over the last dimension of `x`, with `gain` γ and `bias` β of
/// that size.
pub fn norm_act(
    x: &Tensor,
    gain: &Tensor,
    bias: &Tensor,
    eps: f64,
    act: NormAct,
) -> Result<Tensor> {
    x.contiguous()?.apply_op3(
        gain,
        bias,
        NormActOp {
            eps: eps as f32,
            act,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;

    #[test]
    fn norm_act_matches_the_composed_layer_norm() {
        let (x, g, b) = (var(&[6, 8], 4), var(&[8], 5), var(&[8], 6));
        let eps = 1e-3;
        let centred = x
            .broadcast_sub(&x.mean_keepdim(D::Minus1).unwrap())
            .unwrap();
        let var_ = centred.sqr().unwrap().mean_keepdim(D::Minus1).unwrap();
        let ln = centred
            .broadcast_div(&(var_ + eps).unwrap().sqrt().unwrap())
            .unwrap()
            .broadcast_mul(&g)
            .unwrap()
            .broadcast_add(&b)
            .unwrap();
        let fused = |act| norm_act(&x, &g, &b, eps, act).unwrap();
        same(fused(NormAct::Identity), ln.clone(), &[&x, &g, &b], 1e-4);
        same(
            fused(NormAct::Silu),
            candle_nn::ops::silu(&ln).unwrap(),
            &[&x, &g, &b],
            1e-4,
        );
    }
}
