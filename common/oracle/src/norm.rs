//! Layer normalisation with a backward pass, optionally fused with the SiLU that follows it.
//!
//! `y = (x − mean(x)) / √(var(x) + ε) · γ + β` over the last dimension. candle-nn's `LayerNorm`
//! takes a fused kernel without a backward pass whenever its input is contiguous, which silently
//! stops gradients; this one runs [`kernels::norm_act`], which has its own.

use crate::kernels;
use candle_core::{Result, Tensor};
use candle_nn::{Init, VarBuilder};
use ctxrace_nn::kernels::NormAct;

/// A layer normalisation with learned gain `γ` (`weight`) and offset `β` (`bias`).
#[derive(Clone, Debug)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    /// A normalisation over `size` features; `γ = 1`, `β = 0` at the start.
    pub fn new(size: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(size, "weight", Init::Const(1.0))?,
            bias: vb.get_with_hints(size, "bias", Init::Const(0.0))?,
            eps,
        })
    }

    /// `act(LayerNorm(x))`.
    pub fn forward_act(&self, x: &Tensor, act: NormAct) -> Result<Tensor> {
        kernels::norm_act(x, &self.weight, &self.bias, self.eps, act)
    }

    /// `(γ, β, ε)`, for kernels that fuse the normalisation with the layer before it.
    pub fn parts(&self) -> (&Tensor, &Tensor, f64) {
        (&self.weight, &self.bias, self.eps)
    }

    /// The same normalisation on detached (shared) parameters.
    pub fn frozen(&self) -> Self {
        Self {
            weight: self.weight.detach(),
            bias: self.bias.detach(),
            eps: self.eps,
        }
    }
}

impl candle_core::Module for LayerNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_act(x, NormAct::Identity)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ParamStore;
    use candle_core::{Device, Module, Var};

    #[test]
    fn normalises_and_passes_gradients() {
        let ps = ParamStore::new();
        let ln = LayerNorm::new(4, 1e-5, ps.builder()).unwrap();
        let x = Var::from_tensor(&Tensor::new(&[[1.0f32, 2.0, 3.0, 6.0]], &Device::Cpu).unwrap())
            .unwrap();
        let y = ln.forward(x.as_tensor()).unwrap();
        let v: Vec<f32> = y.flatten_all().unwrap().to_vec1().unwrap();
        // mean 3, variance (4 + 1 + 0 + 9) / 4 = 3.5
        for (got, xi) in v.iter().zip([1.0f32, 2.0, 3.0, 6.0]) {
            assert!((got - (xi - 3.0) / (3.5f32 + 1e-5).sqrt()).abs() < 1e-5);
        }
        let w = Tensor::new(&[[1.0f32, 0.0, 0.0, 0.0]], &Device::Cpu).unwrap();
        let grads = y.mul(&w).unwrap().sum_all().unwrap().backward().unwrap();
        let g: Vec<f32> = grads
            .get(x.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert!(g.iter().all(|v| v.abs() > 1e-4), "{g:?}");
    }
}
