//! A fully connected layer `y = x Wᵀ + b` on the fused [`linear`](crate::kernels::linear)
//! kernel, with the parameter names and shapes of candle-nn's `Linear` (`weight` `[out, in]`,
//! `bias` `[out]`).

use super::norm::LayerNorm;
use crate::kernels;
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use ctxrace_nn::kernels::NormAct;
use std::ops::Range;

/// A linear layer, with or without a bias.
#[derive(Clone, Debug)]
pub struct Dense {
    /// `W` `[out, in]`.
    weight: Tensor,
    bias: Option<Tensor>,
    /// Input columns that are mostly zero ([`Dense::sparse_inputs`]).
    sparse_inputs: Option<Range<usize>>,
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
        Ok(Self {
            weight,
            bias,
            sparse_inputs: None,
        })
    }

    /// The same layer told that its input columns `columns` are mostly zero (a one-hot latent):
    /// its products go over their non-zeros only ([`kernels`]' `sparse_inputs`), with the same
    /// results for any input.
    pub fn sparse_inputs(self, columns: Range<usize>) -> Self {
        Self {
            sparse_inputs: Some(columns),
            ..self
        }
    }

    /// `W` `[out, in]`.
    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// `b` `[out]`, if the layer has one.
    pub fn bias(&self) -> Option<&Tensor> {
        self.bias.as_ref()
    }

    /// The input columns the layer was told are mostly zero ([`Dense::sparse_inputs`]).
    pub fn sparse_columns(&self) -> Option<&Range<usize>> {
        self.sparse_inputs.as_ref()
    }

    /// `x Wᵀ + b` for `x` `[N, in]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        kernels::linear(
            x,
            &self.weight,
            self.bias.as_ref(),
            self.sparse_inputs.clone(),
        )
    }

    /// `act(ln(x Wᵀ + b))` in one operation ([`kernels::linear_norm_act`]) when the layer has
    /// no bias (as before every LayerNorm); otherwise as two.
    pub fn forward_norm_act(&self, x: &Tensor, ln: &LayerNorm, act: NormAct) -> Result<Tensor> {
        if self.bias.is_some() {
            return ln.forward_act(&self.forward(x)?, act);
        }
        let sparse = self.sparse_inputs.clone();
        kernels::linear_norm_act(x, &self.weight, ln.parts(), act, sparse)
    }

    /// The same layer on detached parameters: gradients pass to its input but not to its weights
    /// (which it shares, so it follows every update of the original).
    pub fn frozen(&self) -> Self {
        Self {
            weight: self.weight.detach(),
            bias: self.bias.as_ref().map(Tensor::detach),
            sparse_inputs: self.sparse_inputs.clone(),
        }
    }
}
