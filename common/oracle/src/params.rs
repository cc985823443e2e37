//! Trainable parameters: a candle [`VarMap`] whose values come from ctxrace's own seeded generator
//! (candle's CPU generator cannot be seeded), and their exchange as safetensors bytes.
//!
//! Initialisation, in sorted name order so that a seed always gives the same network: matrices
//! `[out, in]` uniform in `±1/√in` (PyTorch's default for linear layers), vectors named `*.bias`
//! zero, other vectors (LayerNorm gains) left at one.

use candle_core::{DType, Device, Result, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A named set of trainable tensors on the CPU.
#[derive(Clone)]
pub struct ParamStore {
    map: VarMap,
}

impl Default for ParamStore {
    fn default() -> Self {
        Self { map: VarMap::new() }
    }
}

impl ParamStore {
    /// An empty store.
    pub fn new() -> Self {
        Self::default()
    }

    /// A builder that creates parameters in this store (f32, CPU).
    pub fn builder(&self) -> VarBuilder<'static> {
        VarBuilder::from_varmap(&self.map, DType::F32, &Device::Cpu)
    }

    /// All parameters, sorted by name.
    pub fn named(&self) -> Vec<(String, Var)> {
        let data = self.map.data().lock().expect("parameter map poisoned");
        let mut v: Vec<_> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    /// All parameters, sorted by name (for an optimiser).
    pub fn vars(&self) -> Vec<Var> {
        self.named().into_iter().map(|(_, v)| v).collect()
    }

    /// The parameters whose names start with one of the `prefixes` (as `prefix.`), sorted by
    /// name.
    pub fn vars_under(&self, prefixes: &[&str]) -> Vec<Var> {
        self.named()
            .into_iter()
            .filter(|(name, _)| prefixes.iter().any(|p| name.starts_with(&format!("{p}."))))
            .map(|(_, v)| v)
            .collect()
    }

    /// Number of scalar parameters.
    pub fn count(&self) -> usize {
        self.named().iter().map(|(_, v)| v.elem_count()).sum()
    }

    /// Re-initialises every parameter from `seed` (see the module doc).
    pub fn init(&self, seed: u64) -> Result<()> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for (name, var) in self.named() {
            let dims = var.dims().to_vec();
            let value = match dims.as_slice() {
                [out, inp] => {
                    let bound = 1.0 / (*inp as f32).sqrt();
                    let data: Vec<f32> = (0..out * inp)
                        .map(|_| rng.random_range(-bound..=bound))
                        .collect();
                    Tensor::from_vec(data, (*out, *inp), &Device::Cpu)?
                }
                [_] if name.ends_with("bias") => var.zeros_like()?,
                _ => continue,
            };
            var.set(&value)?;
        }
        Ok(())
    }

    /// Every parameter as safetensors bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let named = self.named();
        let tensors: Vec<(String, Tensor)> = named
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        safetensors::serialize(tensors.iter().map(|(k, t)| (k.as_str(), t)), None)
            .map_err(|e| candle_core::Error::Msg(format!("serialising parameters: {e}")))
    }

    /// Loads parameters from safetensors bytes; every name and shape must match this store.
    pub fn load_bytes(&self, bytes: &[u8]) -> Result<()> {
        let loaded = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)?;
        let named = self.named();
        if loaded.len() != named.len() {
            candle_core::bail!(
                "weights hold {} tensors, the network has {}; they are of different architectures",
                loaded.len(),
                named.len()
            );
        }
        for (name, var) in &named {
            let Some(t) = loaded.get(name) else {
                candle_core::bail!(
                    "weights lack tensor '{name}'; they are of a different architecture"
                );
            };
            if t.dims() != var.dims() {
                candle_core::bail!(
                    "tensor '{name}' has shape {:?} in the weights, {:?} in the network",
                    t.dims(),
                    var.dims()
                );
            }
            var.set(&t.to_dtype(DType::F32)?)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_layer(seed: u64) -> (ParamStore, candle_nn::Linear, candle_nn::LayerNorm) {
        let ps = ParamStore::new();
        let vb = ps.builder();
        let lin = candle_nn::linear(3, 4, vb.pp("fc")).unwrap();
        let ln = candle_nn::layer_norm(4, 1e-3, vb.pp("ln")).unwrap();
        ps.init(seed).unwrap();
        (ps, lin, ln)
    }

    #[test]
    fn a_seed_gives_the_same_weights_and_bytes_round_trip_bit_exact() {
        let (a, ..) = two_layer(3);
        let (b, ..) = two_layer(3);
        let (c, ..) = two_layer(4);
        let bytes = a.to_bytes().unwrap();
        assert_eq!(bytes, b.to_bytes().unwrap());
        assert_ne!(bytes, c.to_bytes().unwrap());
        c.load_bytes(&bytes).unwrap();
        assert_eq!(c.to_bytes().unwrap(), bytes);
        assert_eq!(a.count(), 3 * 4 + 4 + 4 + 4);
        // biases zero, LayerNorm gains one, weights within the bound
        for (name, v) in a.named() {
            let vals: Vec<f32> = v.flatten_all().unwrap().to_vec1().unwrap();
            match name.as_str() {
                "fc.bias" | "ln.bias" => assert!(vals.iter().all(|&x| x == 0.0)),
                "ln.weight" => assert!(vals.iter().all(|&x| x == 1.0)),
                "fc.weight" => assert!(vals.iter().all(|&x| x.abs() <= 1.0 / 3f32.sqrt())),
                other => panic!("unexpected {other}"),
            }
        }
    }

    #[test]
    fn loading_other_architectures_is_an_error() {
        let (a, ..) = two_layer(0);
        let other = ParamStore::new();
        candle_nn::linear(3, 5, other.builder().pp("fc")).unwrap();
        let err = other
            .load_bytes(&a.to_bytes().unwrap())
            .unwrap_err()
            .to_string();
        assert!(err.contains("architecture"), "{err}");
        assert!(a.load_bytes(b"not safetensors").is_err());
    }
}
