//! The unimix categorical latents: straight-through one-hot samples and the KL divergence.

use super::*;

/// A unimix categorical over `classes`: `p = (1 − unimix) softmax(l) + unimix / classes`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Unimix {
    pub(crate) classes: usize,
    pub(crate) unimix: f32,
}

/// `$f::<S>(c, args…)` with the class count `c` a constant when it is [`PAPER_CLASSES`], so
/// that the compiler unrolls the loops over a variable's classes into a few vector instructions.
macro_rules! with_classes {
    ($classes:expr, $f:ident::<S>($($arg:expr),*)) => {
        match $classes {
            PAPER_CLASSES => $f::<S>(PAPER_CLASSES, $($arg),*),
            c => $f::<S>(c, $($arg),*),
        }
    };
}

/// The first index of `x` whose value is `v` (0 if none), without a branch per value: the
/// equalities as bits of a mask, 32 values at a time.
#[inline(always)]
fn first_equal(x: &[f32], v: f32) -> usize {
    for (i, chunk) in x.chunks(32).enumerate() {
        let mut mask = 0u32;
        for (b, &w) in chunk.iter().enumerate() {
            mask |= u32::from(w == v) << b;
        }
        if mask != 0 {
            return 32 * i + mask.trailing_zeros() as usize;
        }
    }
    0
}

/// The classes of each of the paper's latent variables (REFERENCE §5: 16 x 16).
const PAPER_CLASSES: usize = 16;

impl Unimix {
    /// `(s, p)`: the softmax of `l` and the mixed probabilities.
    #[inline(always)]
    fn probs<S: Isa>(&self, l: &[f32], s: &mut [f32], p: &mut [f32]) {
        softmax_into::<S>(l, s);
        let floor = self.unimix / self.classes as f32;
        for (pk, &sk) in p.iter_mut().zip(s.iter()) {
            *pk = (1.0 - self.unimix) * sk + floor;
        }
    }
}

vectorised! {
    /// One-hot Gumbel-max samples into `out` (zeros) of the unimix categoricals with logits `l`,
    /// from uniforms `u`, all in rows of `classes`: the argmax of `ln p + g` with
    /// `g = −ln(−ln U)`, i.e. of `p / (−ln U)`.
    pub(crate) fn sample_rows(dist: Unimix, l: &[f32], u: &[f32], out: &mut [f32]) {
        #[inline(always)]
        fn rows<S: Isa>(c: usize, dist: Unimix, l: &[f32], u: &[f32], out: &mut [f32]) {
            let (mut s, mut p, mut score) = (vec![0f32; c], vec![0f32; c], vec![0f32; c]);
            let rows = l.chunks_exact(c).zip(u.chunks_exact(c));
            for ((lr, ur), o) in rows.zip(out.chunks_exact_mut(c)) {
                dist.probs::<S>(lr, &mut s, &mut p);
                for ((sc, &pk), &uk) in score.iter_mut().zip(&p).zip(ur) {
                    *sc = pk / -ln(uk);
                }
                // the first class of the largest score, from a mask of the classes that have it
                let best = lane_max::<S>(&score);
                o[first_equal(&score, best)] = 1.0;
            }
        }
        with_classes!(dist.classes, rows::<S>(dist, l, u, out))
    }
}

vectorised! {
    /// `dl ← ∂/∂l` of the unimix probabilities' gradient `g`, rows of `classes` (the
    /// straight-through sample's backward pass).
    pub(crate) fn probs_rows_bwd(dist: Unimix, l: &[f32], g: &[f32], dl: &mut [f32]) {
        #[inline(always)]
        fn rows<S: Isa>(c: usize, dist: Unimix, l: &[f32], g: &[f32], dl: &mut [f32]) {
            let (mut s, mut p) = (vec![0f32; c], vec![0f32; c]);
            let rows = l.chunks_exact(c).zip(g.chunks_exact(c));
            for ((lr, gr), d) in rows.zip(dl.chunks_exact_mut(c)) {
                dist.probs::<S>(lr, &mut s, &mut p);
                unimix_softmax_backward::<S>(&s, gr, 1.0 - dist.unimix, d);
            }
        }
        with_classes!(dist.classes, rows::<S>(dist, l, g, dl))
    }
}

vectorised! {
    /// `out_i ← Σ_v KL(p_a ‖ p_b)` over the variables (`classes` logits each) of the rows of
    /// `per_row` logits of `la` and `lb`.
    pub(crate) fn kl_rows(dist: Unimix, la: &[f32], lb: &[f32], per_row: usize, out: &mut [f32]) {
        #[inline(always)]
        fn rows<S: Isa>(
            c: usize,
            dist: Unimix,
            l: (&[f32], &[f32]),
            per_row: usize,
            out: &mut [f32],
        ) {
            let mut buf = vec![0f32; 4 * c];
            let (sa, rest) = buf.split_at_mut(c);
            let (pa, rest) = rest.split_at_mut(c);
            let (sb, pb) = rest.split_at_mut(c);
            let rows = l.0.chunks_exact(per_row).zip(l.1.chunks_exact(per_row));
            for ((ra, rb), o) in rows.zip(out.iter_mut()) {
                for (va, vb) in ra.chunks_exact(c).zip(rb.chunks_exact(c)) {
                    dist.probs::<S>(va, sa, pa);
                    dist.probs::<S>(vb, sb, pb);
                    *o += lane_sum::<S>(pa, pb, |a, b| a * (ln(a) - ln(b)));
                }
            }
        }
        with_classes!(dist.classes, rows::<S>(dist, (la, lb), per_row, out))
    }
}

vectorised! {
    /// The gradients of the rows' KL divergences of [`kl_rows`] with output gradients `g` (one
    /// per row of `per_row` logits): `∂/∂l_a` into `da` and `∂/∂l_b` into `db`, each left empty
    /// when not wanted. Through the probabilities, `∂KL/∂p_a = ln p_a − ln p_b + 1` and
    /// `∂KL/∂p_b = −p_a / p_b`.
    pub(crate) fn kl_rows_bwd(
        dist: Unimix,
        la: &[f32],
        lb: &[f32],
        g: &[f32],
        per_row: usize,
        da: &mut [f32],
        db: &mut [f32],
    ) {
        #[inline(always)]
        fn rows<S: Isa>(
            c: usize,
            dist: Unimix,
            (la, lb): (&[f32], &[f32]),
            (g, per_row): (&[f32], usize),
            da: &mut [f32],
            db: &mut [f32],
        ) {
            let keep = 1.0 - dist.unimix;
            let mut buf = vec![0f32; 5 * c];
            let (sa, rest) = buf.split_at_mut(c);
            let (pa, rest) = rest.split_at_mut(c);
            let (sb, rest) = rest.split_at_mut(c);
            let (pb, dp) = rest.split_at_mut(c);
            let variables = la.chunks_exact(c).zip(lb.chunks_exact(c)).enumerate();
            for (i, (va, vb)) in variables {
                let gi = g[i * c / per_row];
                dist.probs::<S>(va, sa, pa);
                dist.probs::<S>(vb, sb, pb);
                if let Some(out) = da.get_mut(i * c..(i + 1) * c) {
                    for ((d, &a), &b) in dp.iter_mut().zip(pa.iter()).zip(pb.iter()) {
                        *d = gi * (ln(a) - ln(b) + 1.0);
                    }
                    unimix_softmax_backward::<S>(sa, dp, keep, out);
                }
                if let Some(out) = db.get_mut(i * c..(i + 1) * c) {
                    for ((d, &a), &b) in dp.iter_mut().zip(pa.iter()).zip(pb.iter()) {
                        *d = -gi * a / b;
                    }
                    unimix_softmax_backward::<S>(sb, dp, keep, out);
                }
            }
        }
        with_classes!(dist.classes, rows::<S>(dist, (la, lb), (g, per_row), da, db))
    }
}

#[cfg(any(test, feature = "oracle"))]
struct StraightThrough(Unimix);

#[cfg(any(test, feature = "oracle"))]
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
#[cfg(any(test, feature = "oracle"))]
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

#[cfg(any(test, feature = "oracle"))]
struct Kl(Unimix);

#[cfg(any(test, feature = "oracle"))]
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
#[cfg(any(test, feature = "oracle"))]
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
