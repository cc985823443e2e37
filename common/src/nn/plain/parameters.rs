//! A network's trainable tensors where they live: visited by name for the optimiser, the
//! seeded initialisation, Polyak averaging and safetensors files, so that the networks the
//! learner trains are the ones it saves and the actors run, with no copy in between.
//!
//! Initialisation ([`init`]), in sorted name order over all the networks given, so that a seed
//! always gives the same weights: matrices `[out, in]` uniform in `±1/√in` (PyTorch's default
//! for linear layers), vectors named `*.bias` zero, other vectors (LayerNorm gains, a learned
//! initial state, `log α`) left at the value the network was built with
//! ([`crate::nn::Weights::initial`]).

use crate::nn::weights::WeightsError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safetensors::tensor::TensorView;
use safetensors::Dtype;

/// One trainable tensor: its name in a weights file, its shape and its values (row-major).
#[derive(Clone, Debug)]
pub struct NamedTensor<'a> {
    /// The name (`encoder.l0.fc.weight`).
    pub name: &'a str,
    /// The shape.
    pub shape: Vec<usize>,
    /// The values.
    pub values: &'a [f32],
}

/// A network's trainable tensors, in an order fixed by its architecture.
pub trait Parameters {
    /// Every tensor.
    fn tensors(&self) -> Vec<NamedTensor<'_>>;

    /// Calls `f(i, values)` for the `i`-th tensor of [`Parameters::tensors`], for each, letting
    /// it change the values; then refreshes whatever the network derives from them.
    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32]));
}

/// Several networks trained or saved together, as one (their tensors one after the other).
impl Parameters for [&mut dyn Parameters] {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        self.iter().flat_map(|n| n.tensors()).collect()
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        update_each(self.iter_mut().map(|n| &mut **n), f);
    }
}

/// [`Parameters::update`] of several networks as one: `f`'s index runs on from one network's
/// tensors to the next's (for a struct of networks implementing [`Parameters`]).
pub fn update_each<'a: 'b, 'b>(
    nets: impl IntoIterator<Item = &'b mut (dyn Parameters + 'a)>,
    f: &mut dyn FnMut(usize, &mut [f32]),
) {
    let mut first = 0;
    for net in nets {
        let count = net.tensors().len();
        net.update(&mut |i, values| f(first + i, values));
        first += count;
    }
}

/// The number of scalar parameters of `net`.
pub fn count<P: Parameters + ?Sized>(net: &P) -> usize {
    net.tensors().iter().map(|t| t.values.len()).sum()
}

/// Draws `net`'s initial weights from `seed` (see the module doc).
pub fn init<P: Parameters + ?Sized>(net: &mut P, seed: u64) {
    let tensors = net.tensors();
    let mut order: Vec<usize> = (0..tensors.len()).collect();
    order.sort_by(|&a, &b| tensors[a].name.cmp(tensors[b].name));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut drawn: Vec<Option<Vec<f32>>> = vec![None; tensors.len()];
    for i in order {
        let t = &tensors[i];
        drawn[i] = match t.shape.as_slice() {
            [out, inp] => {
                let bound = 1.0 / (*inp as f32).sqrt();
                Some(
                    (0..out * inp)
                        .map(|_| rng.random_range(-bound..=bound))
                        .collect(),
                )
            }
            [len] if t.name.ends_with("bias") => Some(vec![0.0; *len]),
            _ => None,
        };
    }
    net.update(&mut |i, values| {
        if let Some(new) = &drawn[i] {
            values.copy_from_slice(new);
        }
    });
}

/// `net`'s tensors as safetensors bytes (`f32`, under their names).
pub fn to_safetensors<P: Parameters + ?Sized>(net: &P) -> Result<Vec<u8>, WeightsError> {
    let tensors = net.tensors();
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|t| t.values.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let views = tensors
        .iter()
        .zip(&bytes)
        .map(|(t, b)| {
            TensorView::new(Dtype::F32, t.shape.clone(), b)
                .map(|view| (t.name, view))
                .map_err(|e| WeightsError::Format(format!("tensor '{}': {e}", t.name)))
        })
        .collect::<Result<Vec<_>, _>>()?;
    safetensors::serialize(views, None).map_err(|e| WeightsError::Format(e.to_string()))
}

/// Sets `net`'s tensors to those of the safetensors `bytes`: every name and shape must match,
/// and no tensor may be left over; on an error `net` is unchanged.
pub fn load_safetensors<P: Parameters + ?Sized>(
    net: &mut P,
    bytes: &[u8],
) -> Result<(), WeightsError> {
    let mut weights = crate::nn::Weights::from_safetensors(bytes)?;
    let loaded = net
        .tensors()
        .iter()
        .map(|t| weights.take(t.name, &t.shape))
        .collect::<Result<Vec<_>, _>>()?;
    weights.finish()?;
    net.update(&mut |i, values| values.copy_from_slice(&loaded[i]));
    Ok(())
}

/// `target ← (1 − τ) target + τ source`, tensor by tensor (networks of one architecture).
pub fn polyak<P: Parameters + ?Sized>(target: &mut P, source: &P, tau: f64) {
    let source = source.tensors();
    let (keep, take) = ((1.0 - tau) as f32, tau as f32);
    target.update(&mut |i, values| {
        for (t, &s) in values.iter_mut().zip(source[i].values) {
            *t = *t * keep + s * take;
        }
    });
}

/// `target ← source`, tensor by tensor (networks of one architecture).
pub fn copy<P: Parameters + ?Sized>(target: &mut P, source: &P) {
    let source = source.tensors();
    target.update(&mut |i, values| values.copy_from_slice(source[i].values));
}
