//! The candle-held form of [`crate::adam::Adam`], until every network trains in place.
//!
//! CandleAdam (Kingma & Ba 2015) with global-norm gradient clipping, and moments that can be saved:
//! candle's `AdamW` keeps its moments private, so a resumed run would restart them from zero.
//!
//! For each parameter `w` with gradient `g`, at step `t` (from 1):
//!
//! ```text
//! g ← g · min(1, clip / ‖G‖)          ‖G‖: the norm of all gradients together
//! m ← β₁ m + (1 − β₁) g,    v ← β₂ v + (1 − β₂) g²
//! w ← w − lr · (m / (1 − β₁ᵗ)) / (√(v / (1 − β₂ᵗ)) + ε)
//! ```
//!
//! (PyTorch's `CandleAdam` without weight decay). The update runs on plain `f32` buffers, one pass
//! per parameter.

use candle_core::backprop::GradStore;
use candle_core::{bail, DType, Device, Result, Tensor, Var};
use ctxrace_common::nn::kernels::{adam_update_in_place, squared_norm, AdamStep};
use std::collections::HashMap;

/// First-moment decay `β₁`.
const BETA1: f64 = 0.9;
/// Second-moment decay `β₂`.
const BETA2: f64 = 0.999;

/// An CandleAdam optimiser over a fixed list of variables.
pub struct CandleAdam {
    vars: Vec<Var>,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    t: u64,
    lr: f64,
    eps: f64,
    clip: f64,
}

impl CandleAdam {
    /// CandleAdam over `vars` with learning rate `lr`, `ε = eps` and the gradient norm clipped to
    /// `clip` (`f64::INFINITY`: no clipping).
    pub fn new(vars: Vec<Var>, lr: f64, eps: f64, clip: f64) -> Self {
        let zeros = || vars.iter().map(|v| vec![0f32; v.elem_count()]).collect();
        Self {
            m: zeros(),
            v: zeros(),
            vars,
            t: 0,
            lr,
            eps,
            clip,
        }
    }

    /// One step with `grads` (variables without a gradient are left alone); returns the
    /// gradient norm before clipping. A non-finite norm skips the step, so that one bad batch
    /// cannot poison the weights. The gradients are read and the weights updated where candle
    /// stores them, without copies.
    pub fn step(&mut self, grads: &GradStore) -> Result<f64> {
        let found: Vec<Option<&Tensor>> = self
            .vars
            .iter()
            .map(|var| grads.get(var.as_tensor()))
            .collect();
        let mut sq = 0f64;
        for g in found.iter().flatten() {
            sq += squared_norm(g)?;
        }
        let norm = sq.sqrt();
        if !norm.is_finite() {
            return Ok(norm);
        }
        let scale = if norm > self.clip {
            (self.clip / norm) as f32
        } else {
            1.0
        };
        self.t += 1;
        let t = self.t as i32;
        let lr_t = (self.lr / (1.0 - BETA1.powi(t))) as f32;
        let v_corr = (1.0 / (1.0 - BETA2.powi(t))) as f32;
        let coefficients = AdamStep {
            scale,
            beta1: BETA1 as f32,
            beta2: BETA2 as f32,
            lr_t,
            v_corr,
            eps: self.eps as f32,
        };
        let moments = self.m.iter_mut().zip(self.v.iter_mut());
        for ((var, g), (m, v)) in self.vars.iter().zip(&found).zip(moments) {
            if let Some(g) = g {
                adam_update_in_place(var.as_tensor(), g, (m, v), coefficients)?;
            }
        }
        Ok(norm)
    }

    /// The moments and step counter as safetensors bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let dev = &Device::Cpu;
        let mut tensors = HashMap::new();
        for (i, (m, v)) in self.m.iter().zip(&self.v).enumerate() {
            tensors.insert(format!("m.{i}"), Tensor::from_slice(m, m.len(), dev)?);
            tensors.insert(format!("v.{i}"), Tensor::from_slice(v, v.len(), dev)?);
        }
        tensors.insert("t".into(), Tensor::new(&[self.t as f64], dev)?);
        safetensors::serialize(tensors.iter().map(|(k, t)| (k.as_str(), t)), None)
            .map_err(|e| candle_core::Error::Msg(format!("serialising optimiser state: {e}")))
    }

    /// Restores what [`CandleAdam::to_bytes`] wrote for the same variables.
    pub fn load_bytes(&mut self, bytes: &[u8]) -> Result<()> {
        let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)?;
        let get = |name: &str, len: usize| -> Result<Vec<f32>> {
            let Some(t) = tensors.get(name) else {
                bail!("optimiser state has no `{name}`");
            };
            let data = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
            if data.len() != len {
                bail!(
                    "optimiser state `{name}` has {} values, the parameter {len}",
                    data.len()
                );
            }
            Ok(data)
        };
        let mut m = Vec::with_capacity(self.vars.len());
        let mut v = Vec::with_capacity(self.vars.len());
        for (i, var) in self.vars.iter().enumerate() {
            m.push(get(&format!("m.{i}"), var.elem_count())?);
            v.push(get(&format!("v.{i}"), var.elem_count())?);
        }
        if tensors.len() != 2 * self.vars.len() + 1 {
            bail!(
                "optimiser state holds {} tensors, expected {}",
                tensors.len(),
                2 * self.vars.len() + 1
            );
        }
        let t = match tensors.get("t") {
            Some(t) => t.to_dtype(DType::F64)?.to_vec1::<f64>()?[0],
            None => bail!("optimiser state has no step counter `t`"),
        };
        (self.m, self.v, self.t) = (m, v, t as u64);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_step_moves_each_weight_by_lr_against_its_gradient_sign() {
        // at t = 1, m̂ = g and v̂ = g², so Δw = −lr g / (|g| + ε)
        let w = Var::from_vec(vec![1f32, -2.0, 0.5], 3, &Device::Cpu).unwrap();
        let mut adam = CandleAdam::new(vec![w.clone()], 0.1, 1e-8, f64::INFINITY);
        let loss = (w.as_tensor() * &Tensor::new(&[3f32, -1.0, 0.0], &Device::Cpu).unwrap())
            .unwrap()
            .sum_all()
            .unwrap();
        let norm = adam.step(&loss.backward().unwrap()).unwrap();
        assert!((norm - 10f64.sqrt()).abs() < 1e-6);
        let after = w.to_vec1::<f32>().unwrap();
        for (a, e) in after.iter().zip([0.9f32, -1.9, 0.5]) {
            assert!((a - e).abs() < 1e-6, "{after:?}");
        }
    }

    #[test]
    fn clipping_scales_the_gradient_and_state_round_trips() {
        let w = Var::from_vec(vec![0f32, 0.0], 2, &Device::Cpu).unwrap();
        let target = Tensor::new(&[3f32, 4.0], &Device::Cpu).unwrap();
        let mut adam = CandleAdam::new(vec![w.clone()], 0.01, 1e-8, 1.0);
        let loss = || {
            (w.as_tensor() - &target)
                .unwrap()
                .sqr()
                .unwrap()
                .sum_all()
                .unwrap()
        };
        // gradient −2·(3, 4), norm 10, clipped to 1: m = 0.1 · (−0.6, −0.8)
        assert!((adam.step(&loss().backward().unwrap()).unwrap() - 10.0).abs() < 1e-5);
        assert!((adam.m[0][0] + 0.06).abs() < 1e-7 && (adam.m[0][1] + 0.08).abs() < 1e-7);
        for _ in 0..3 {
            adam.step(&loss().backward().unwrap()).unwrap();
        }
        let bytes = adam.to_bytes().unwrap();
        let mut other = CandleAdam::new(vec![w.clone()], 0.01, 1e-8, 1.0);
        other.load_bytes(&bytes).unwrap();
        assert_eq!(
            (other.m.clone(), other.v.clone(), other.t),
            (adam.m.clone(), adam.v.clone(), 4)
        );
        let mut wrong = CandleAdam::new(
            vec![Var::zeros(3, DType::F32, &Device::Cpu).unwrap()],
            0.01,
            1e-8,
            1.0,
        );
        assert!(wrong
            .load_bytes(&bytes)
            .unwrap_err()
            .to_string()
            .contains("3"));
    }
}
