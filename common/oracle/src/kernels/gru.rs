//! DreamerV3's GRU update from its normalised gates, as a candle op around [`gru_rows`].

use super::*;
use ctxrace_nn::kernels::{gru_rows, gru_rows_bwd};

struct GruGates;

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
