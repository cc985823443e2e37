//! DreamerV3's GRU update from its normalised gates.

use super::*;

/// The shift of the update gate, `u = σ(û − UPDATE_SHIFT)` (DreamerV3's `update_bias = -1`),
/// which keeps the state at first.
pub const UPDATE_SHIFT: f32 = 1.0;

/// The gate values of one element: `(r, c, u)` with `c = tanh(r ĉ)` and
/// `u = σ(û − UPDATE_SHIFT)`.
#[inline(always)]
fn gates(pr: f32, pc: f32, pu: f32) -> (f32, f32, f32) {
    let r = sigmoid(pr);
    (r, tanh(r * pc), sigmoid(pu - UPDATE_SHIFT))
}

vectorised! {
    /// `out` (whole rows of `size`) ← the GRU update of the gate rows `p` and states `h`.
    pub fn gru_rows(p: &[f32], h: &[f32], out: &mut [f32], size: usize) {
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
    pub fn gru_rows_bwd(p: &[f32], h: &[f32], g: &[f32], dp: &mut [f32], dh: &mut [f32], size: usize) {
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
