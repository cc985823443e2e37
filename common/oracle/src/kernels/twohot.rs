//! The two-hot heads as candle ops: the decoded value and the soft cross-entropy against
//! two-hot targets, around [`decode_rows`] and [`cross_entropy_rows`].

use super::*;
use ctxrace_nn::kernels::{
    cross_entropy_rows, cross_entropy_rows_bwd, decode_rows, decode_rows_bwd,
};

struct TwohotDecode {
    bins: Vec<f32>,
}

impl CustomOp1 for TwohotDecode {
    fn name(&self) -> &'static str {
        "ctxrace-twohot-decode"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = cpu_slice(s, l)?;
        let k = self.bins.len();
        let mut out = vec![0f32; x.len() / k];
        decode_rows(x, &self.bins, &mut out);
        let dims = l.shape().dims();
        Ok((CpuStorage::F32(out), Shape::from(&dims[..dims.len() - 1])))
    }

    fn bwd(&self, logits: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let dl = read(logits, |x| {
            read(grad, |g| {
                let mut dl = vec![0f32; x.len()];
                decode_rows_bwd(x, &self.bins, g, &mut dl);
                Ok(dl)
            })
        })?;
        Ok(Some(Tensor::from_vec(dl, logits.shape(), logits.device())?))
    }
}

/// `symexp(Σ_k softmax(l)_k b_k)` over the last dimension of `logits` `[…, K]` for bins `b`.
pub fn twohot_decode(logits: &Tensor, bins: &[f32]) -> Result<Tensor> {
    if logits.dims().last() != Some(&bins.len()) {
        bail!(
            "twohot_decode: logits {:?} for {} bins",
            logits.dims(),
            bins.len()
        );
    }
    logits.contiguous()?.apply_op1(TwohotDecode {
        bins: bins.to_vec(),
    })
}

struct SoftCrossEntropy;

impl CustomOp2 for SoftCrossEntropy {
    fn name(&self) -> &'static str {
        "ctxrace-soft-cross-entropy"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (l, t) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        let (rows, k) = l1.shape().dims2()?;
        if l.len() != t.len() {
            bail!(
                "soft_cross_entropy: logits {:?}, targets {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let mut out = vec![0f32; rows];
        if rows > 0 && k > 0 {
            cross_entropy_rows(l, t, &mut out);
        }
        Ok((CpuStorage::F32(out), Shape::from(rows)))
    }

    fn bwd(
        &self,
        logits: &Tensor,
        target: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        if wants_grad(target) {
            bail!("soft_cross_entropy: the targets must be detached");
        }
        dims2(logits)?;
        let dl = read(logits, |l| {
            read(target, |t| {
                read(grad, |g| {
                    let mut dl = vec![0f32; l.len()];
                    if !dl.is_empty() {
                        cross_entropy_rows_bwd(l, t, g, &mut dl);
                    }
                    Ok(dl)
                })
            })
        })?;
        Ok((
            Some(Tensor::from_vec(dl, logits.shape(), logits.device())?),
            None,
        ))
    }
}

/// `−Σ_k t_k log softmax(l)_k` `[N]` of logits `[N, K]` against (detached) targets `[N, K]`.
pub fn soft_cross_entropy(logits: &Tensor, target: &Tensor) -> Result<Tensor> {
    logits
        .contiguous()?
        .apply_op2(&target.contiguous()?, SoftCrossEntropy)
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;

    #[test]
    fn twohot_heads_match_the_composed_softmax() {
        // 37 bins: two full vector lanes of the reductions and a remainder
        let l = var(&[5, 37], 15);
        let bins: Vec<f32> = (0..37).map(|k| -3.0 + 0.2 * k as f32).collect();
        let b = Tensor::new(bins.as_slice(), &Device::Cpu).unwrap();
        let m = candle_nn::ops::softmax(&l, D::Minus1)
            .unwrap()
            .broadcast_mul(&b)
            .unwrap()
            .sum(D::Minus1)
            .unwrap();
        let symexp = m
            .sign()
            .unwrap()
            .mul(&(m.abs().unwrap().exp().unwrap() - 1.0).unwrap())
            .unwrap();
        same(twohot_decode(&l, &bins).unwrap(), symexp, &[&l], 1e-4);

        let t = var(&[5, 37], 16).as_tensor().abs().unwrap().detach();
        let composed = t
            .mul(&candle_nn::ops::log_softmax(&l, D::Minus1).unwrap())
            .unwrap()
            .sum(D::Minus1)
            .unwrap()
            .neg()
            .unwrap();
        same(soft_cross_entropy(&l, &t).unwrap(), composed, &[&l], 1e-4);
    }
}
