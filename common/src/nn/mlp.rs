//! Multi-layer perceptrons: `Linear → [LayerNorm] → activation` blocks, then an optional output layer.

use super::dense::Dense;
use super::kernels::NormAct;
use super::norm::LayerNorm;
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

/// Hidden-layer activation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// `x σ(x)`, with LayerNorm before it (DreamerV3).
    SiluNorm,
    /// `max(x, 0)` without normalisation (the paper's SAC networks).
    Relu,
}

/// An MLP: `layers` hidden blocks of width `units`, then a linear head to `out` (if given).
#[derive(Clone, Debug)]
pub struct Mlp {
    hidden: Vec<(Dense, Option<LayerNorm>)>,
    head: Option<Dense>,
    act: Activation,
}

impl Mlp {
    /// Builds the layers under `vb` (`l{i}.fc`, `l{i}.ln`, `out`).
    pub fn new(
        input: usize,
        units: usize,
        layers: usize,
        out: Option<usize>,
        act: Activation,
        vb: VarBuilder,
    ) -> Result<Self> {
        let mut hidden = Vec::with_capacity(layers);
        let mut width = input;
        for i in 0..layers {
            let vb_i = vb.pp(format!("l{i}"));
            let norm = act == Activation::SiluNorm;
            // with a LayerNorm after it the linear layer's bias is redundant
            let fc = Dense::new(width, units, !norm, vb_i.pp("fc"))?;
            let ln = if norm {
                Some(LayerNorm::new(units, 1e-3, vb_i.pp("ln"))?)
            } else {
                None
            };
            hidden.push((fc, ln));
            width = units;
        }
        let head = match out {
            Some(o) => Some(Dense::new(width, o, true, vb.pp("out"))?),
            None => None,
        };
        Ok(Self { hidden, head, act })
    }

    /// The same network on detached (shared) parameters: gradients reach its input only.
    pub fn frozen(&self) -> Self {
        Self {
            hidden: self
                .hidden
                .iter()
                .map(|(fc, ln)| (fc.frozen(), ln.as_ref().map(LayerNorm::frozen)))
                .collect(),
            head: self.head.as_ref().map(Dense::frozen),
            act: self.act,
        }
    }

    /// The same network for a loop that applies it many times (see [`Dense::looped`]).
    pub fn looped(&self) -> Result<Self> {
        Ok(Self {
            hidden: self
                .hidden
                .iter()
                .map(|(fc, ln)| Ok((fc.looped()?, ln.clone())))
                .collect::<Result<_>>()?,
            head: self.head.as_ref().map(Dense::looped).transpose()?,
            act: self.act,
        })
    }
}

impl Module for Mlp {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = x.clone();
        for (fc, ln) in &self.hidden {
            h = match ln {
                Some(ln) => fc.forward_norm_act(&h, ln, NormAct::Silu)?,
                None => fc.forward(&h)?.relu()?,
            };
        }
        match &self.head {
            Some(head) => head.forward(&h),
            None => Ok(h),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::ParamStore;
    use candle_core::{DType, Device};

    #[test]
    fn every_parameter_gets_a_gradient() {
        for act in [Activation::SiluNorm, Activation::Relu] {
            let ps = ParamStore::new();
            let mlp = Mlp::new(3, 8, 2, Some(2), act, ps.builder().pp("mlp")).unwrap();
            ps.init(5).unwrap();
            let x = Tensor::randn(0f32, 1.0, (4, 3), &Device::Cpu).unwrap();
            let y = mlp.forward(&x).unwrap();
            assert_eq!(y.dims(), &[4, 2]);
            let grads = y.sqr().unwrap().sum_all().unwrap().backward().unwrap();
            for (name, var) in ps.named() {
                let g = grads
                    .get(var.as_tensor())
                    .unwrap_or_else(|| panic!("{act:?}: no gradient for {name}"));
                let norm = g
                    .sqr()
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_dtype(DType::F32)
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap();
                assert!(norm > 0.0, "{act:?}: zero gradient for {name}");
            }
        }
    }
}
