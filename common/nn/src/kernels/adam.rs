//! The elementwise part of an Adam step, vectorised: the optimiser's time goes here for the
//! small networks of SAC, where a step updates more parameters than it multiplies rows.

use super::*;

/// The coefficients of one Adam step (see `ctxrace_learner::adam`): the gradient's clipping
/// `scale`, the moment decays `β₁`, `β₂`, the bias-corrected learning rate `lr / (1 − β₁ᵗ)`, the
/// second moment's correction `1 / (1 − β₂ᵗ)` and `ε`.
#[derive(Clone, Copy, Debug)]
pub struct AdamStep {
    /// Factor on the gradient (global-norm clipping).
    pub scale: f32,
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// `lr / (1 − β₁ᵗ)`.
    pub lr_t: f32,
    /// `1 / (1 − β₂ᵗ)`.
    pub v_corr: f32,
    /// Added to the root of the second moment.
    pub eps: f32,
}

vectorised! {
    /// `m ← β₁ m + (1 − β₁) g̃`, `v ← β₂ v + (1 − β₂) g̃²`, `w ← w − lr_t m / (√(v v_corr) + ε)`
    /// with `g̃ = scale · g`, elementwise over slices of one length.
    fn update(w: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32], c: AdamStep) {
        let (b1, b2) = (c.beta1, c.beta2);
        let moments = m.iter_mut().zip(v.iter_mut());
        for ((w, &g), (m, v)) in w.iter_mut().zip(g).zip(moments) {
            let g = g * c.scale;
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * g * g;
            *w -= c.lr_t * *m / ((*v * c.v_corr).sqrt() + c.eps);
        }
    }
}

vectorised! {
    /// `Σ x²` in `f64` (a gradient's squared norm), in lane-parallel partial sums.
    pub fn sum_of_squares(x: &[f32]) -> f64 {
        let mut acc = [0f64; LANES];
        let chunks = x.chunks_exact(LANES);
        let tail: f64 = chunks.remainder().iter().map(|&v| f64::from(v) * f64::from(v)).sum();
        for c in chunks {
            for l in 0..LANES {
                acc[l] += f64::from(c[l]) * f64::from(c[l]);
            }
        }
        acc.iter().sum::<f64>() + tail
    }
}

/// Buffers of an Adam step that are not all of one length.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("adam_update: {weights} weights, {gradients} gradients, moments of {m} and {v}")]
pub struct AdamLengthError {
    /// Weights.
    pub weights: usize,
    /// Gradients.
    pub gradients: usize,
    /// First moments.
    pub m: usize,
    /// Second moments.
    pub v: usize,
}

/// One Adam step on a parameter `w` with gradient `g` and moments `m`, `v` (all of one length).
pub fn adam_update(
    w: &mut [f32],
    g: &[f32],
    m: &mut [f32],
    v: &mut [f32],
    step: AdamStep,
) -> std::result::Result<(), AdamLengthError> {
    if g.len() != w.len() || m.len() != w.len() || v.len() != w.len() {
        return Err(AdamLengthError {
            weights: w.len(),
            gradients: g.len(),
            m: m.len(),
            v: v.len(),
        });
    }
    update(w, g, m, v, step);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adam_update_matches_the_scalar_formula() {
        let n = 37;
        let mut w: Vec<f32> = (0..n).map(|i| (i as f32 * 0.3).sin()).collect();
        let g: Vec<f32> = (0..n).map(|i| (i as f32 * 0.7).cos()).collect();
        let mut m: Vec<f32> = (0..n).map(|i| 0.01 * i as f32).collect();
        let mut v: Vec<f32> = (0..n).map(|i| 0.02 * i as f32).collect();
        let c = AdamStep {
            scale: 0.5,
            beta1: 0.9,
            beta2: 0.999,
            lr_t: 1e-3,
            v_corr: 2.0,
            eps: 1e-8,
        };
        let (w0, m0, v0) = (w.clone(), m.clone(), v.clone());
        adam_update(&mut w, &g, &mut m, &mut v, c).unwrap();
        for k in 0..n {
            let gk = g[k] * c.scale;
            let mk = c.beta1 * m0[k] + (1.0 - c.beta1) * gk;
            let vk = c.beta2 * v0[k] + (1.0 - c.beta2) * gk * gk;
            let wk = w0[k] - c.lr_t * mk / ((vk * c.v_corr).sqrt() + c.eps);
            assert!((m[k] - mk).abs() < 1e-7 && (v[k] - vk).abs() < 1e-7);
            assert!((w[k] - wk).abs() < 1e-6, "{k}: {} vs {wk}", w[k]);
        }
        let want: f64 = g.iter().map(|&x| f64::from(x) * f64::from(x)).sum();
        assert!((sum_of_squares(&g) - want).abs() < 1e-9);
        assert!(adam_update(&mut w, &g[1..], &mut m, &mut v, c).is_err());
    }
}
