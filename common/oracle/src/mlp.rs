//! The oracle's multi-layer perceptrons (candle modules): `Linear → [LayerNorm] → activation` blocks, then an optional output layer.

use super::dense::Dense;
use super::norm::LayerNorm;
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;
use ctxrace_nn::kernels::NormAct;
use ctxrace_nn::layer::{Activation, LAYER_NORM_EPS};
use std::ops::Range;

/// A hidden block of an [`Mlp`]: a layer and, for [`Activation::SiluNorm`], its normalisation.
pub type HiddenBlock = (Dense, Option<LayerNorm>);

/// An MLP: `layers` hidden blocks of width `units`, then a linear head to `out` (if given).
#[derive(Clone, Debug)]
pub struct Mlp {
    hidden: Vec<HiddenBlock>,
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
                Some(LayerNorm::new(units, LAYER_NORM_EPS, vb_i.pp("ln"))?)
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

    /// The same network told that its input columns `columns` are mostly zero (the one-hot
    /// latent of a state, see [`Dense::sparse_inputs`]).
    pub fn sparse_inputs(mut self, columns: Range<usize>) -> Self {
        match (self.hidden.first_mut(), &mut self.head) {
            (Some((fc, _)), _) | (None, Some(fc)) => *fc = fc.clone().sparse_inputs(columns),
            (None, None) => {}
        }
        self
    }

    /// Its hidden blocks (each a layer and, for [`Activation::SiluNorm`], its normalisation), its
    /// output layer and the hidden activation.
    pub fn parts(&self) -> (&[HiddenBlock], Option<&Dense>, Activation) {
        (&self.hidden, self.head.as_ref(), self.act)
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
    use crate::ParamStore;
    use candle_core::{DType, Device};

    #[test]
    fn sparse_inputs_change_no_value_or_gradient() {
        let ps = ParamStore::new();
        let mlp = Mlp::new(4 + 64, 8, 2, Some(3), Activation::SiluNorm, ps.builder()).unwrap();
        ps.init(7).unwrap();
        let sparse = mlp.clone().sparse_inputs(4..68);
        // rows [h, z]: h dense, z four one-hot variables of 16 classes
        let mut x = vec![0f32; 5 * 68];
        for (i, row) in x.chunks_exact_mut(68).enumerate() {
            row[..4].fill(0.3 * i as f32 - 0.5);
            for s in 0..4 {
                row[4 + 16 * s + (3 * i + s) % 16] = 1.0;
            }
        }
        let x = candle_core::Var::from_vec(x, (5, 68), &Device::Cpu).unwrap();
        let run = |net: &Mlp| {
            let y = net.forward(x.as_tensor()).unwrap();
            let g = y.sqr().unwrap().sum_all().unwrap().backward().unwrap();
            let mut all = vec![y];
            all.extend(
                ps.named()
                    .iter()
                    .map(|(_, v)| g.get(v.as_tensor()).unwrap().clone()),
            );
            all.push(g.get(x.as_tensor()).unwrap().clone());
            all
        };
        for (a, b) in run(&mlp).iter().zip(run(&sparse)) {
            let (a, b) = (a.flatten_all().unwrap(), b.flatten_all().unwrap());
            let diff = (a - b).unwrap().abs().unwrap().max(0).unwrap();
            assert!(diff.to_scalar::<f32>().unwrap() < 1e-5);
        }
    }

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
