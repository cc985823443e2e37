//! A network's weights by name, read from safetensors bytes without an autograd library: the
//! files the learner writes (`policy.safetensors`, a checkpoint's blobs) name each tensor by
//! its place in the network (`l0.fc.weight`, `encoder.l0.ln.bias`, …), `f32`, row-major.
//!
//! A network takes its tensors by name and shape ([`Weights::take`]) and then checks that none
//! is left over ([`Weights::finish`]): weights of another architecture are an error naming the
//! tensor, never a silently different network.

use safetensors::{Dtype, SafeTensors};
use std::collections::BTreeMap;

/// Why weights could not be read, or do not fit the network reading them.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum WeightsError {
    /// The bytes are not a safetensors file.
    #[error("the weights are not a safetensors file: {0}")]
    Format(String),
    /// A tensor is not of 32-bit floats.
    #[error("tensor '{name}' holds {dtype} values, the networks f32")]
    DType {
        /// The tensor's name.
        name: String,
        /// Its element type.
        dtype: String,
    },
    /// The network needs a tensor the weights lack.
    #[error("the weights lack tensor '{0}'; they are of a different architecture")]
    Missing(String),
    /// A tensor's shape differs from the network's.
    #[error("tensor '{name}' has shape {found:?} in the weights, {want:?} in the network")]
    Shape {
        /// The tensor's name.
        name: String,
        /// Its shape in the weights.
        found: Vec<usize>,
        /// The network's shape for it.
        want: Vec<usize>,
    },
    /// The weights hold tensors the network does not have.
    #[error(
        "the weights hold tensors the network does not have ({0}); they are of a different \
         architecture"
    )]
    Unused(String),
}

/// Tensors by name, each its shape and its values.
#[derive(Clone, Debug, Default)]
pub struct Weights {
    tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    /// Every tensor asked for is at its initial value ([`Weights::initial`]).
    initial: bool,
}

impl Weights {
    /// Weights that hold every tensor a network asks for at its construction value: zero, or
    /// the value given to [`Weights::take_or`] (LayerNorm gains one). A network built from
    /// them and then given [`crate::parameters::init`] is a freshly initialised one.
    pub fn initial() -> Self {
        Self {
            tensors: BTreeMap::new(),
            initial: true,
        }
    }

    /// Reads safetensors bytes of `f32` tensors.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self, WeightsError> {
        let file =
            SafeTensors::deserialize(bytes).map_err(|e| WeightsError::Format(e.to_string()))?;
        let mut tensors = BTreeMap::new();
        for (name, view) in file.iter() {
            if view.dtype() != Dtype::F32 {
                return Err(WeightsError::DType {
                    name: name.to_string(),
                    dtype: view.dtype().to_string(),
                });
            }
            let values = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            tensors.insert(name.to_string(), (view.shape().to_vec(), values));
        }
        Ok(Self {
            tensors,
            initial: false,
        })
    }

    /// The shape of tensor `name`, if the weights hold it (and it was not taken).
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.tensors.get(name).map(|(shape, _)| shape.as_slice())
    }

    /// Takes the values of tensor `name`, which must have the shape `shape`.
    pub fn take(&mut self, name: &str, shape: &[usize]) -> Result<Vec<f32>, WeightsError> {
        self.take_or(name, shape, 0.0)
    }

    /// [`Weights::take`], where weights [`Weights::initial`] give every value `initial`.
    pub fn take_or(
        &mut self,
        name: &str,
        shape: &[usize],
        initial: f32,
    ) -> Result<Vec<f32>, WeightsError> {
        if self.initial {
            return Ok(vec![initial; shape.iter().product()]);
        }
        let Some((found, values)) = self.tensors.remove(name) else {
            return Err(WeightsError::Missing(name.to_string()));
        };
        if found != shape {
            return Err(WeightsError::Shape {
                name: name.to_string(),
                found,
                want: shape.to_vec(),
            });
        }
        Ok(values)
    }

    /// Checks that every tensor was taken.
    pub fn finish(self) -> Result<(), WeightsError> {
        if self.tensors.is_empty() {
            return Ok(());
        }
        let names: Vec<&str> = self.tensors.keys().map(String::as_str).collect();
        Err(WeightsError::Unused(names.join(", ")))
    }
}
