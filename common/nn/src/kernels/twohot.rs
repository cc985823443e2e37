//! The two-hot heads: the decoded value and the soft cross-entropy against two-hot targets.

use super::*;

vectorised! {
    /// `out_i ← symexp(Σ_k softmax(x_i)_k b_k)` for the rows `x_i` of `bins.len()` values of `x`.
    pub fn decode_rows(x: &[f32], bins: &[f32], out: &mut [f32]) {
        if bins.is_empty() {
            return;
        }
        let mut p = vec![0f32; bins.len()];
        for (xr, o) in x.chunks_exact(bins.len()).zip(out.iter_mut()) {
            softmax_into::<S>(xr, &mut p);
            let m = lane_sum::<S>(&p, bins, |a, b| a * b);
            *o = m.signum() * (m.abs().exp() - 1.0);
        }
    }
}

vectorised! {
    /// The backward pass of [`decode_rows`]: `dx_ik = g_i e^{|m_i|} p_ik (b_k − m_i)`.
    pub fn decode_rows_bwd(x: &[f32], bins: &[f32], g: &[f32], dx: &mut [f32]) {
        let k = bins.len();
        if k == 0 {
            return;
        }
        let mut p = vec![0f32; k];
        for ((xr, d), &gr) in x.chunks_exact(k).zip(dx.chunks_exact_mut(k)).zip(g) {
            softmax_into::<S>(xr, &mut p);
            let m = lane_sum::<S>(&p, bins, |a, b| a * b);
            let dm = gr * m.abs().exp();
            for j in 0..k {
                d[j] = p[j] * (bins[j] - m) * dm;
            }
        }
    }
}

vectorised! {
    /// `out_i ← Σ_k t_ik (lse(l_i) − l_ik)` for the rows of `l` and `t` (`l.len() / out.len()`
    /// values each).
    pub fn cross_entropy_rows(l: &[f32], t: &[f32], out: &mut [f32]) {
        let k = l.len() / out.len();
        for ((lr, tr), o) in l.chunks_exact(k).zip(t.chunks_exact(k)).zip(out.iter_mut()) {
            let max = lane_max::<S>(lr);
            let lse = max + lane_sum::<S>(lr, lr, |v, _| exp(v - max)).ln();
            *o = lane_sum::<S>(tr, lr, |tk, lk| tk * (lse - lk));
        }
    }
}

vectorised! {
    /// The backward pass of [`cross_entropy_rows`]: `dl_ik = g_i (softmax(l_i)_k Σ_j t_ij − t_ik)`.
    pub fn cross_entropy_rows_bwd(l: &[f32], t: &[f32], g: &[f32], dl: &mut [f32]) {
        let k = l.len() / g.len();
        let mut p = vec![0f32; k];
        for (((lr, tr), d), &gr) in l
            .chunks_exact(k)
            .zip(t.chunks_exact(k))
            .zip(dl.chunks_exact_mut(k))
            .zip(g)
        {
            softmax_into::<S>(lr, &mut p);
            let total = lane_sum::<S>(tr, tr, |v, _| v);
            for j in 0..k {
                d[j] = gr * (p[j] * total - tr[j]);
            }
        }
    }
}
