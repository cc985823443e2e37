//! The oracle's symlog and two-hot regression on candle tensors ([`ctxrace_nn::symlog`]).

use crate::kernels;
use candle_core::{Result, Tensor};
use ctxrace_nn::TwoHot;

/// `sign(x) ln(1 + |x|)`.
pub fn symlog(x: &Tensor) -> Result<Tensor> {
    x.sign()?.mul(&(x.abs()? + 1.0)?.log()?)
}

/// [`TwoHot`]'s encoding, decoding and loss on candle tensors (in scope, they are called as
/// [`TwoHot`]'s own methods).
pub trait TwoHotTensors {
    /// Two-hot targets `[N, K]` for values `y` of shape `[N]` (in the original space).
    fn encode(&self, y: &Tensor) -> Result<Tensor>;

    /// Decodes logits `[…, K]` to values `[…]` in the original space.
    fn decode(&self, logits: &Tensor) -> Result<Tensor>;

    /// Cross-entropy `−Σ_k t_k log softmax(logits)_k` of logits `[N, K]` against the two-hot
    /// targets of `y` `[N]`; returns `[N]`.
    fn loss(&self, logits: &Tensor, y: &Tensor) -> Result<Tensor>;
}

impl TwoHotTensors for TwoHot {
    fn encode(&self, y: &Tensor) -> Result<Tensor> {
        let values: Vec<f32> = y.to_vec1()?;
        let mut out = vec![0f32; values.len() * self.count()];
        self.add_encoded(&values, 1.0, &mut out);
        Tensor::from_vec(out, (values.len(), self.count()), y.device())
    }

    fn decode(&self, logits: &Tensor) -> Result<Tensor> {
        kernels::twohot_decode(logits, self.bins())
    }

    fn loss(&self, logits: &Tensor, y: &Tensor) -> Result<Tensor> {
        kernels::soft_cross_entropy(logits, &self.encode(&y.detach())?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn t(v: &[f32]) -> Tensor {
        Tensor::new(v, &Device::Cpu).unwrap()
    }

    #[test]
    fn symlog_by_hand() {
        let x = t(&[-10.0, -1.0, 0.0, 0.5, 100.0]);
        let got: Vec<f32> = symlog(&x).unwrap().to_vec1().unwrap();
        let want = [-(11f32.ln()), -(2f32.ln()), 0.0, 1.5f32.ln(), 101f32.ln()];
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{g} vs {w}");
        }
    }

    #[test]
    fn twohot_encodes_between_neighbouring_bins_and_decodes_back() {
        // 5 bins over [-2, 2]: -2, -1, 0, 1, 2 (symlog space)
        let th = TwoHot::new(5, -2.0, 2.0);
        // symlog(e^0.25 − 1) = 0.25: 75 % on bin 0, 25 % on bin 1
        let y = t(&[0.25f32.exp() - 1.0, 0.0, 1000.0]);
        let enc: Vec<Vec<f32>> = th.encode(&y).unwrap().to_vec2().unwrap();
        let want = [
            [0.0, 0.0, 0.75, 0.25, 0.0],
            [0.0, 0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 0.0, 1.0],
        ];
        for (row, w) in enc.iter().zip(want) {
            for (a, b) in row.iter().zip(w) {
                assert!((a - b).abs() < 1e-5, "{row:?}");
            }
        }
        // logits equal to log of the encoding decode back to the value (within the bin range)
        let logits = th
            .encode(&t(&[0.7, -3.0]))
            .unwrap()
            .clamp(1e-8, 1.0)
            .unwrap()
            .log()
            .unwrap();
        let dec: Vec<f32> = th.decode(&logits).unwrap().to_vec1().unwrap();
        assert!(
            (dec[0] - 0.7).abs() < 1e-3 && (dec[1] + 3.0).abs() < 1e-3,
            "{dec:?}"
        );
    }

    #[test]
    fn twohot_loss_is_the_cross_entropy() {
        let th = TwoHot::new(3, -1.0, 1.0);
        let logits = Tensor::new(&[[0.0f32, 1.0, 2.0]], &Device::Cpu).unwrap();
        let y = t(&[0.0]); // all weight on the middle bin
        let loss: Vec<f32> = th.loss(&logits, &y).unwrap().to_vec1().unwrap();
        let lse = (1f32 + 1f32.exp() + 2f32.exp()).ln();
        assert!((loss[0] - (lse - 1.0)).abs() < 1e-5);
        assert_eq!(TwoHot::dreamer().count(), 255);
    }
}
