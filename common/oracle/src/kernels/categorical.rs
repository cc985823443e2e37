//! The unimix categorical latents as candle ops: straight-through one-hot samples and the KL
//! divergence, around [`sample_rows`] and [`kl_rows`].

use super::*;
use ctxrace_nn::kernels::{kl_rows, kl_rows_bwd, probs_rows_bwd, sample_rows, Unimix};

struct StraightThrough(Unimix);

impl CustomOp2 for StraightThrough {
    fn name(&self) -> &'static str {
        "ctxrace-straight-through"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (l, u) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        let c = self.0.classes;
        if l.len() != u.len() || l.len() % c != 0 {
            bail!(
                "straight_through_sample: logits {:?}, uniforms {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let mut out = vec![0f32; l.len()];
        sample_rows(self.0, l, u, &mut out);
        let rows = l1.shape().dims()[0];
        Ok((CpuStorage::F32(out), Shape::from((rows, l.len() / rows))))
    }

    fn bwd(
        &self,
        logits: &Tensor,
        _uniform: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        if !wants_grad(logits) {
            return Ok((None, None));
        }
        let dl = read(logits, |l| {
            read(grad, |g| {
                let mut dl = vec![0f32; l.len()];
                probs_rows_bwd(self.0, l, g, &mut dl);
                Ok(dl)
            })
        })?;
        Ok((
            Some(Tensor::from_vec(dl, logits.shape(), logits.device())?),
            None,
        ))
    }
}

/// A straight-through one-hot sample `[N, S·C]` of the unimix categoricals with logits
/// `[N, S, C]`, drawn by Gumbel-max from uniforms `U ∈ (0, 1)` of the same shape: forward the
/// exact one-hot, backward the gradient of the probabilities.
pub fn straight_through_sample(logits: &Tensor, uniform: &Tensor, unimix: f64) -> Result<Tensor> {
    let classes = *logits.dims().last().unwrap_or(&0);
    if logits.rank() != 3 || classes == 0 {
        bail!(
            "straight_through_sample: logits [N, S, C], got {:?}",
            logits.dims()
        );
    }
    let op = StraightThrough(Unimix {
        classes,
        unimix: unimix as f32,
    });
    logits.contiguous()?.apply_op2(&uniform.contiguous()?, op)
}

struct Kl(Unimix);

impl CustomOp2 for Kl {
    fn name(&self) -> &'static str {
        "ctxrace-categorical-kl"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (la, lb) = (cpu_slice(s1, l1)?, cpu_slice(s2, l2)?);
        if la.len() != lb.len() {
            bail!(
                "categorical_kl: logits {:?} and {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let rows = l1.shape().dims()[0];
        let (c, per_row) = (self.0.classes, la.len() / rows.max(1));
        let mut out = vec![0f32; rows];
        if c > 0 && per_row > 0 {
            kl_rows(self.0, la, lb, per_row, &mut out);
        }
        Ok((CpuStorage::F32(out), Shape::from(rows)))
    }

    fn bwd(
        &self,
        la_t: &Tensor,
        lb_t: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (want_a, want_b) = (wants_grad(la_t), wants_grad(lb_t));
        if !want_a && !want_b {
            return Ok((None, None));
        }
        let (da, db) = read(la_t, |la| {
            read(lb_t, |lb| {
                read(grad, |g| {
                    let per_row = la.len() / g.len().max(1);
                    let mut da = vec![0f32; if want_a { la.len() } else { 0 }];
                    let mut db = vec![0f32; if want_b { lb.len() } else { 0 }];
                    kl_rows_bwd(self.0, la, lb, g, per_row, &mut da, &mut db);
                    Ok((da, db))
                })
            })
        })?;
        let dev = la_t.device();
        Ok((
            want_a
                .then(|| Tensor::from_vec(da, la_t.shape(), dev))
                .transpose()?,
            want_b
                .then(|| Tensor::from_vec(db, lb_t.shape(), dev))
                .transpose()?,
        ))
    }
}

/// `KL(p_a ‖ p_b)` `[N]` of the unimix categoricals with logits `[N, S, C]`, summed over the
/// `S` variables.
pub fn categorical_kl(logits_a: &Tensor, logits_b: &Tensor, unimix: f64) -> Result<Tensor> {
    let classes = *logits_a.dims().last().unwrap_or(&0);
    if logits_a.rank() != 3 || classes == 0 || logits_a.dims() != logits_b.dims() {
        bail!(
            "categorical_kl: logits [N, S, C] of one shape, got {:?} and {:?}",
            logits_a.dims(),
            logits_b.dims()
        );
    }
    let op = Kl(Unimix {
        classes,
        unimix: unimix as f32,
    });
    logits_a
        .contiguous()?
        .apply_op2(&logits_b.contiguous()?, op)
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;
    use ctxrace_nn::kernels::PAPER_CLASSES;

    /// The composed unimix probabilities of logits `[N, S, C]`.
    fn probs(l: &Tensor, unimix: f64) -> Tensor {
        let c = l.dims()[2] as f64;
        ((candle_nn::ops::softmax(l, D::Minus1).unwrap() * (1.0 - unimix)).unwrap() + unimix / c)
            .unwrap()
    }

    #[test]
    fn straight_through_samples_are_one_hot_with_the_probability_gradient() {
        // any class count, and the paper's, whose loops are unrolled
        for c in [4, PAPER_CLASSES] {
            samples_are_one_hot_with_the_probability_gradient(c);
        }
    }

    fn samples_are_one_hot_with_the_probability_gradient(c: usize) {
        let l = var(&[3, 2, c], 12);
        let u = Tensor::full(0.5f32, (3, 2, c), &Device::Cpu).unwrap();
        let z = straight_through_sample(&l, &u, 0.01).unwrap();
        assert_eq!(z.dims(), &[3, 2 * c]);
        let p = probs(&l, 0.01);
        // equal uniforms: the sample is the most likely class
        let want = p
            .argmax(D::Minus1)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<u32>()
            .unwrap();
        for (row, k) in vals(&z).chunks(c).zip(want) {
            let mut onehot = vec![0f32; c];
            onehot[k as usize] = 1.0;
            assert_eq!(row, onehot);
        }
        let composed = (z.detach().reshape((3, 2, c)).unwrap() + &p)
            .unwrap()
            .sub(&p.detach())
            .unwrap()
            .reshape((3, 2 * c))
            .unwrap();
        same(z, composed, &[&l], 1e-5);
    }

    #[test]
    fn categorical_kl_matches_the_composed_divergence() {
        for c in [4, PAPER_CLASSES] {
            kl_matches_the_composed_divergence(c);
        }
    }

    fn kl_matches_the_composed_divergence(c: usize) {
        let (a, b) = (var(&[3, 2, c], 13), var(&[3, 2, c], 14));
        let (pa, pb) = (probs(&a, 0.01), probs(&b, 0.01));
        let composed = pa
            .mul(&(pa.log().unwrap() - pb.log().unwrap()).unwrap())
            .unwrap()
            .sum(D::Minus1)
            .unwrap()
            .sum(D::Minus1)
            .unwrap();
        same(
            categorical_kl(&a, &b, 0.01).unwrap(),
            composed,
            &[&a, &b],
            1e-4,
        );
        let g = categorical_kl(&a, &b.as_tensor().detach(), 0.01)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(g.get(&a).is_some() && g.get(&b).is_none());
    }
}
