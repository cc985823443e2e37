//! The unimix categorical latents: straight-through one-hot samples and the KL divergence.

use super::*;

/// A unimix categorical over `classes`: `p = (1 − unimix) softmax(l) + unimix / classes`.
#[derive(Clone, Copy, Debug)]
pub struct Unimix {
    /// The classes of each variable.
    pub classes: usize,
    /// The weight of the uniform mixture.
    pub unimix: f32,
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

/// The classes of each of the paper's latent variables (REFERENCE §5: 16 x 16), for which the
/// loops over a variable's classes are unrolled.
pub const PAPER_CLASSES: usize = 16;

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
    pub fn sample_rows(dist: Unimix, l: &[f32], u: &[f32], out: &mut [f32]) {
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
    pub fn probs_rows_bwd(dist: Unimix, l: &[f32], g: &[f32], dl: &mut [f32]) {
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
    pub fn kl_rows(dist: Unimix, la: &[f32], lb: &[f32], per_row: usize, out: &mut [f32]) {
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
    pub fn kl_rows_bwd(
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
