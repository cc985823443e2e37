//! DreamerV3's return maths: λ-returns over an imagined trajectory (computed on plain buffers by
//! [`crate::behaviour`]; here as the tests' candle oracle) and the percentile return normaliser.
//!
//! λ-return, for rewards `r_{t+1}`, continue probabilities `c_{t+1}` and values `v_t` of the
//! states `s_0 … s_H` of a trajectory:
//!
//! ```text
//! R_H = v_H,    R_t = r_{t+1} + γ c_{t+1} ((1 − λ) v_{t+1} + λ R_{t+1})
//! ```
//!
//! Return normalisation: `lo ← d·lo + (1 − d)·P5(R)`, `hi ← d·hi + (1 − d)·P95(R)` from zero
//! (no bias correction, as DreamerV3 does), and returns are divided by `S = max(1, hi − lo)`.

#[cfg(test)]
use candle_core::{Result, Tensor};
use serde::{Deserialize, Serialize};

/// λ-returns `R_0 … R_{H−1}` `[H, N]` from `reward` `[H, N]` (`r_1 … r_H`), `cont` `[H, N]`
/// (`c_1 … c_H`) and `value` `[H + 1, N]` (`v_0 … v_H`), as candle tensors differentiable in all
/// three: the oracle of the hand-differentiated returns of [`crate::behaviour`].
#[cfg(test)]
pub(crate) fn lambda_returns(
    reward: &Tensor,
    cont: &Tensor,
    value: &Tensor,
    gamma: f64,
    lambda: f64,
) -> Result<Tensor> {
    let horizon = reward.dim(0)?;
    if cont.dim(0)? != horizon || value.dim(0)? != horizon + 1 {
        candle_core::bail!(
            "λ-returns need H rewards, H continues and H + 1 values; got {}, {}, {}",
            horizon,
            cont.dim(0)?,
            value.dim(0)?
        );
    }
    let mut next = value.get(horizon)?;
    let mut out = Vec::with_capacity(horizon);
    for t in (0..horizon).rev() {
        let blend = ((value.get(t + 1)? * (1.0 - lambda))? + (next * lambda)?)?;
        next = (reward.get(t)? + (cont.get(t)? * gamma)?.mul(&blend)?)?;
        out.push(next.clone());
    }
    out.reverse();
    Tensor::stack(&out, 0)
}

/// The `q`-quantile (`q ∈ [0, 1]`) of ascending `sorted` values, interpolating linearly between
/// neighbours (NumPy's and PyTorch's default); 0 for no values.
pub fn quantile(sorted: &[f32], q: f64) -> f64 {
    let Some(last) = sorted.len().checked_sub(1) else {
        return 0.0;
    };
    let pos = q.clamp(0.0, 1.0) * last as f64;
    let below = pos.floor() as usize;
    let above = (below + 1).min(last);
    let frac = pos - below as f64;
    sorted[below] as f64 * (1.0 - frac) + sorted[above] as f64 * frac
}

/// The EMA of the low and high percentiles of the returns (see the module doc).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReturnNorm {
    /// EMA of the low percentile.
    pub low: f64,
    /// EMA of the high percentile.
    pub high: f64,
    /// EMA decay `d`.
    pub decay: f64,
    /// Low percentile as a fraction (0.05).
    pub low_q: f64,
    /// High percentile as a fraction (0.95).
    pub high_q: f64,
}

impl ReturnNorm {
    /// A normaliser at zero.
    pub fn new(decay: f64, low_q: f64, high_q: f64) -> Self {
        Self {
            low: 0.0,
            high: 0.0,
            decay,
            low_q,
            high_q,
        }
    }

    /// Moves the EMAs towards the percentiles of `values` (non-finite values are ignored).
    pub fn update(&mut self, values: &[f32]) {
        let mut sorted: Vec<f32> = values.iter().copied().filter(|v| v.is_finite()).collect();
        if sorted.is_empty() {
            return;
        }
        sorted.sort_by(f32::total_cmp);
        let d = self.decay;
        self.low = d * self.low + (1.0 - d) * quantile(&sorted, self.low_q);
        self.high = d * self.high + (1.0 - d) * quantile(&sorted, self.high_q);
    }

    /// The divisor `S = max(1, hi − lo)`.
    pub fn scale(&self) -> f64 {
        (self.high - self.low).max(1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn lambda_returns_by_hand() {
        let dev = Device::Cpu;
        // rewards r_1..r_3, continues c_1..c_3, values v_0..v_3; γ = 0.9, λ = 0.5
        let r = Tensor::new(&[[1f32], [2.0], [3.0]], &dev).unwrap();
        let c = Tensor::new(&[[1f32], [1.0], [0.5]], &dev).unwrap();
        let v = Tensor::new(&[[0f32], [10.0], [20.0], [30.0]], &dev).unwrap();
        let got: Vec<f32> = lambda_returns(&r, &c, &v, 0.9, 0.5)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        // R_3 = 30
        // R_2 = 3 + 0.9·0.5·(0.5·30 + 0.5·30)    = 16.5
        // R_1 = 2 + 0.9·1·(0.5·20 + 0.5·16.5)    = 18.425
        // R_0 = 1 + 0.9·1·(0.5·10 + 0.5·18.425)  = 13.79125
        let want = [13.79125f32, 18.425, 16.5];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-4, "{got:?}");
        }
        assert!(lambda_returns(&r, &c, &r, 0.9, 0.5).is_err());
    }

    #[test]
    fn percentile_normaliser_by_hand() {
        let values: Vec<f32> = (0..=100).map(|v| v as f32).collect();
        let mut shuffled = values.clone();
        shuffled.reverse();
        assert_eq!(quantile(&values, 0.05), 5.0);
        assert_eq!(quantile(&values, 0.95), 95.0);
        assert_eq!(quantile(&[1.0, 2.0], 0.25), 1.25);
        let mut norm = ReturnNorm::new(0.99, 0.05, 0.95);
        norm.update(&shuffled);
        assert!((norm.low - 0.05).abs() < 1e-12 && (norm.high - 0.95).abs() < 1e-12);
        assert_eq!(norm.scale(), 1.0); // range 0.9 < 1
        norm.update(&shuffled);
        // lo = 0.99·0.05 + 0.01·5 = 0.0995, hi = 0.99·0.95 + 0.01·95 = 1.8905
        assert!((norm.low - 0.0995).abs() < 1e-12, "{}", norm.low);
        assert!((norm.high - 1.8905).abs() < 1e-12, "{}", norm.high);
        assert!((norm.scale() - 1.791).abs() < 1e-12);
        norm.update(&[f32::NAN]);
        assert!((norm.high - 1.8905).abs() < 1e-12);
    }
}
