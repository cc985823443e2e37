//! The two-hot heads: the decoded value and the soft cross-entropy against two-hot targets.

use super::*;

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
        let mut p = vec![0f32; k];
        for (i, o) in out.iter_mut().enumerate() {
            softmax_into(&x[i * k..(i + 1) * k], &mut p);
            let m: f32 = p.iter().zip(&self.bins).map(|(a, b)| a * b).sum();
            *o = m.signum() * (m.abs().exp() - 1.0);
        }
        let dims = l.shape().dims();
        Ok((CpuStorage::F32(out), Shape::from(&dims[..dims.len() - 1])))
    }

    fn bwd(&self, logits: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let k = self.bins.len();
        let dl = read(logits, |x| {
            read(grad, |g| {
                let mut dl = vec![0f32; x.len()];
                let mut p = vec![0f32; k];
                for (i, d) in dl.chunks_mut(k).enumerate() {
                    let r = i;
                    softmax_into(&x[r * k..(r + 1) * k], &mut p);
                    let m: f32 = p.iter().zip(&self.bins).map(|(a, b)| a * b).sum();
                    let dm = g[r] * m.abs().exp();
                    for j in 0..k {
                        d[j] = p[j] * (self.bins[j] - m) * dm;
                    }
                }
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
        for (i, o) in out.iter_mut().enumerate() {
            let at = i * k;
            let (lr, tr) = (&l[at..at + k], &t[at..at + k]);
            let max = lr.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let lse = max + lr.iter().map(|&v| exp(v - max)).sum::<f32>().ln();
            *o = tr.iter().zip(lr).map(|(tk, lk)| tk * (lse - lk)).sum();
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
        let (_, k) = dims2(logits)?;
        let dl = read(logits, |l| {
            read(target, |t| {
                read(grad, |g| {
                    let mut dl = vec![0f32; l.len()];
                    let mut p = vec![0f32; k];
                    for (i, d) in dl.chunks_mut(k).enumerate() {
                        let r = i;
                        softmax_into(&l[r * k..(r + 1) * k], &mut p);
                        let tr = &t[r * k..(r + 1) * k];
                        let total: f32 = tr.iter().sum();
                        for j in 0..k {
                            d[j] = g[r] * (p[j] * total - tr[j]);
                        }
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
        let l = var(&[5, 7], 15);
        let bins: Vec<f32> = (0..7).map(|k| -3.0 + k as f32).collect();
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

        let t = var(&[5, 7], 16).as_tensor().abs().unwrap().detach();
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
