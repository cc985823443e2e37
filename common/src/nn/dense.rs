//! A fully connected layer `y = x Wᵀ + b` on the fused [`linear`](super::kernels::linear)
//! kernel, with the parameter names and shapes of candle-nn's `Linear` (`weight` `[out, in]`,
//! `bias` `[out]`).

use super::kernels;
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

/// A linear layer, with or without a bias.
#[derive(Clone, Debug)]
pub struct Dense {
    weight: Tensor,
    bias: Option<Tensor>,
}

impl Dense {
    /// A layer from `input` to `output` features built under `vb`.
    pub fn new(input: usize, output: usize, bias: bool, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get_with_hints(
            (output, input),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bias = if bias {
            Some(vb.get_with_hints(output, "bias", candle_nn::Init::Const(0.0))?)
        } else {
            None
        };
        Ok(Self { weight, bias })
    }

    /// `x Wᵀ + b` for `x` `[N, in]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        kernels::linear(x, &self.weight, self.bias.as_ref())
    }

    /// The same layer on detached parameters: gradients pass to its input but not to its weights
    /// (which it shares, so it follows every update of the original).
    pub fn frozen(&self) -> Self {
        Self {
            weight: self.weight.detach(),
            bias: self.bias.as_ref().map(Tensor::detach),
        }
    }
}
