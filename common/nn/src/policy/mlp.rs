//! A policy trained outside ctxrace (PyTorch, JAX, numpy), brought in as an MLP in one documented
//! safetensors file, so that the command line races, draws and evaluates it as it does its own
//! agents (`ctxrace race --policy policy.safetensors`, `ctxrace eval policy.safetensors`).
//!
//! **The format** ([`MLP_FORMAT`]): `f32` tensors `layers.{i}.weight` of shape `[out, in]` and
//! `layers.{i}.bias` of shape `[out]` for `i = 0, 1, …` (the first layer's `in` the input's size,
//! each next layer's `in` the previous `out`, the last `out` 2), and the file's metadata
//! `format = "ctxrace-mlp-policy/1"`, `activation` (`tanh`, `relu` or `silu`, between layers),
//! `inputs` (`scan`: the LiDAR scan; `scan+context`: the scan then the context `(c_v, c_θ)`, as
//! Python's `obs_mode="scan+context"`) and `output` (`clip`: the last layer's values clipped to
//! `[-1, 1]`; `tanh`: squashed by `tanh`). The action is `(steering, speed)` in `[-1, 1]`, as
//! the ego's; the policy is deterministic and keeps no state. Python writes it with
//! `ctxrace.save_mlp_policy`.

use super::{PolicyError, Result, ACT_DIM};
use crate::weights::Weights;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use std::collections::HashMap;

/// The `format` metadata value of an MLP policy file.
pub const MLP_FORMAT: &str = "ctxrace-mlp-policy/1";

/// Whether `path` names an MLP policy file (a file `*.safetensors`) rather than a trained
/// agent's checkpoint or run folder: the one rule the ego and the rivals read paths by.
pub fn is_mlp_file(path: &std::path::Path) -> bool {
    path.is_file() && path.extension().is_some_and(|e| e == "safetensors")
}

/// The largest MLP policy file read (256 MiB: 64M weights, far beyond a racing policy's).
pub const MAX_MLP_FILE_BYTES: u64 = 256 << 20;

/// The bytes of the MLP policy file `path`, refused above [`MAX_MLP_FILE_BYTES`] before any is
/// read.
pub fn read_mlp_file(path: &std::path::Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let file = std::fs::File::open(path)?;
    let len = file.metadata()?.len();
    if len > MAX_MLP_FILE_BYTES {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{len} bytes: an MLP policy file holds at most {MAX_MLP_FILE_BYTES}"),
        ));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(MAX_MLP_FILE_BYTES).read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// The nonlinearity between an [`MlpPolicy`]'s layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpActivation {
    /// `tanh x`.
    Tanh,
    /// `max(x, 0)`.
    Relu,
    /// `x sigmoid(x)`.
    Silu,
}

/// What an [`MlpPolicy`] reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpInputs {
    /// The LiDAR scan.
    Scan,
    /// The scan, then the context `(c_v, c_θ)`.
    ScanContext,
}

/// How an [`MlpPolicy`]'s last layer becomes the action.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpOutput {
    /// Clipped to `[-1, 1]`.
    Clip,
    /// Squashed by `tanh`.
    Tanh,
}

/// The metadata names and values of each choice, one list, its first the default: the
/// `activation` choices.
pub const ACTIVATIONS: [(&str, MlpActivation); 3] = [
    ("tanh", MlpActivation::Tanh),
    ("relu", MlpActivation::Relu),
    ("silu", MlpActivation::Silu),
];
/// The `inputs` choices.
pub const INPUTS: [(&str, MlpInputs); 2] = [
    ("scan", MlpInputs::Scan),
    ("scan+context", MlpInputs::ScanContext),
];
/// The `output` choices.
pub const OUTPUTS: [(&str, MlpOutput); 2] = [("clip", MlpOutput::Clip), ("tanh", MlpOutput::Tanh)];

/// One layer: `y = W x + b`, `W` row-major `[out, in]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Linear {
    /// The weights, `out × in` row-major.
    pub weight: Vec<f32>,
    /// The biases, `out`.
    pub bias: Vec<f32>,
}

impl Linear {
    /// Inputs of the layer.
    fn inputs(&self) -> usize {
        self.weight.len() / self.bias.len().max(1)
    }
}

/// An MLP policy in the format of the module's docs.
#[derive(Clone, Debug, PartialEq)]
pub struct MlpPolicy {
    layers: Vec<Linear>,
    activation: MlpActivation,
    inputs: MlpInputs,
    output: MlpOutput,
    /// The input and each layer's output, reused from step to step.
    work: Vec<Vec<f32>>,
}

/// An error naming what is wrong with an MLP policy file.
fn bad(message: String) -> PolicyError {
    PolicyError::Mlp(format!(
        "{message} (an MLP policy file is {MLP_FORMAT}: see ctxrace_nn::policy::mlp)"
    ))
}

/// The choice metadata `key` names, from `choices`.
fn choice<T: Copy>(meta: &HashMap<String, String>, key: &str, choices: &[(&str, T)]) -> Result<T> {
    let names: Vec<&str> = choices.iter().map(|(n, _)| *n).collect();
    let value = meta
        .get(key)
        .ok_or_else(|| bad(format!("the metadata lacks '{key}' ({})", names.join(", "))))?;
    choices
        .iter()
        .find(|(n, _)| n == value)
        .map(|&(_, v)| v)
        .ok_or_else(|| bad(format!("{key} = '{value}' is none of {}", names.join(", "))))
}

/// The metadata name of `value` among `choices`.
fn name_of<T: PartialEq>(choices: &[(&'static str, T)], value: &T) -> &'static str {
    choices
        .iter()
        .find(|(_, v)| v == value)
        .map_or("", |(n, _)| n)
}

impl MlpPolicy {
    /// A policy of `layers` (each layer's inputs the previous one's outputs, the last with
    /// [`ACT_DIM`] outputs) for observations of `obs_dim` beams.
    pub fn new(
        layers: Vec<Linear>,
        activation: MlpActivation,
        inputs: MlpInputs,
        output: MlpOutput,
        obs_dim: usize,
    ) -> Result<Self> {
        let want_in = obs_dim
            + if inputs == MlpInputs::ScanContext {
                2
            } else {
                0
            };
        let mut width = want_in;
        for (i, l) in layers.iter().enumerate() {
            if l.bias.is_empty() || l.weight.len() != l.bias.len() * width {
                return Err(bad(format!(
                    "layer {i} takes {} inputs where {width} arrive ({} weights, {} biases)",
                    l.inputs(),
                    l.weight.len(),
                    l.bias.len()
                )));
            }
            if let Some(bad_at) = l.weight.iter().chain(&l.bias).position(|v| !v.is_finite()) {
                return Err(bad(format!(
                    "layer {i} holds a value that is not finite (its value {bad_at}, weights first)"
                )));
            }
            width = l.bias.len();
        }
        if layers.is_empty() || width != ACT_DIM {
            return Err(bad(format!(
                "the last layer gives {width} values; the action is {ACT_DIM} (steering, speed)"
            )));
        }
        let mut work = vec![vec![0.0; want_in]];
        work.extend(layers.iter().map(|l| vec![0.0; l.bias.len()]));
        Ok(Self {
            layers,
            activation,
            inputs,
            output,
            work,
        })
    }

    /// [`MlpPolicy::new`] with its choices named as the file's metadata names them
    /// (`activation`, `inputs`, `output`).
    pub fn named(
        layers: Vec<Linear>,
        activation: &str,
        inputs: &str,
        output: &str,
        obs_dim: usize,
    ) -> Result<Self> {
        let meta = HashMap::from([
            ("activation".to_string(), activation.to_string()),
            ("inputs".to_string(), inputs.to_string()),
            ("output".to_string(), output.to_string()),
        ]);
        Self::new(
            layers,
            choice(&meta, "activation", &ACTIVATIONS)?,
            choice(&meta, "inputs", &INPUTS)?,
            choice(&meta, "output", &OUTPUTS)?,
            obs_dim,
        )
    }

    /// Reads a policy file's bytes for observations of `obs_dim` beams.
    pub fn from_safetensors(bytes: &[u8], obs_dim: usize) -> Result<Self> {
        let (_, header) =
            SafeTensors::read_metadata(bytes).map_err(|e| bad(format!("not safetensors: {e}")))?;
        let meta = header.metadata().clone().unwrap_or_default();
        if meta.get("format").map(String::as_str) != Some(MLP_FORMAT) {
            return Err(bad(format!(
                "its metadata's format is {:?}, not '{MLP_FORMAT}'",
                meta.get("format")
            )));
        }
        let activation = choice(&meta, "activation", &ACTIVATIONS)?;
        let inputs = choice(&meta, "inputs", &INPUTS)?;
        let output = choice(&meta, "output", &OUTPUTS)?;
        let mut weights = Weights::from_safetensors(bytes).map_err(|e| bad(e.to_string()))?;
        let mut layers = Vec::new();
        while let Some(&[out, input]) = weights.shape(&format!("layers.{}.weight", layers.len())) {
            let i = layers.len();
            let mut take = |name: String, shape: &[usize]| {
                weights.take(&name, shape).map_err(|e| bad(e.to_string()))
            };
            layers.push(Linear {
                weight: take(format!("layers.{i}.weight"), &[out, input])?,
                bias: take(format!("layers.{i}.bias"), &[out])?,
            });
        }
        weights.finish().map_err(|e| bad(e.to_string()))?;
        Self::new(layers, activation, inputs, output, obs_dim)
    }

    /// The file's bytes (the module's format).
    pub fn to_safetensors(&self) -> Result<Vec<u8>> {
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = self
            .layers
            .iter()
            .enumerate()
            .flat_map(|(i, l)| {
                let le = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<_>>();
                [
                    (
                        format!("layers.{i}.weight"),
                        vec![l.bias.len(), l.inputs()],
                        le(&l.weight),
                    ),
                    (format!("layers.{i}.bias"), vec![l.bias.len()], le(&l.bias)),
                ]
            })
            .collect();
        let views = bytes
            .iter()
            .map(|(name, shape, data)| {
                TensorView::new(Dtype::F32, shape.clone(), data)
                    .map(|v| (name.as_str(), v))
                    .map_err(|e| bad(e.to_string()))
            })
            .collect::<Result<Vec<_>>>()?;
        let meta = HashMap::from([
            ("format".to_string(), MLP_FORMAT.to_string()),
            (
                "activation".into(),
                name_of(&ACTIVATIONS, &self.activation).into(),
            ),
            ("inputs".into(), name_of(&INPUTS, &self.inputs).into()),
            ("output".into(), name_of(&OUTPUTS, &self.output).into()),
        ]);
        safetensors::serialize(views, Some(meta)).map_err(|e| bad(e.to_string()))
    }

    /// Beams of the LiDAR frame it reads.
    pub fn frame_dim(&self) -> usize {
        self.work[0].len()
            - if self.inputs == MlpInputs::ScanContext {
                2
            } else {
                0
            }
    }

    /// The action for observation `obs` under the context `[c_v, c_θ]`.
    pub fn act(&mut self, obs: &[f32], context: [f32; 2]) -> Result<[f32; ACT_DIM]> {
        let want = self.frame_dim();
        if obs.len() != want {
            return Err(PolicyError::Observation {
                found: obs.len(),
                want,
            });
        }
        self.work[0][..want].copy_from_slice(obs);
        if self.inputs == MlpInputs::ScanContext {
            self.work[0][want..].copy_from_slice(&context);
        }
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            let (done, rest) = self.work.split_at_mut(i + 1);
            let (x, y) = (&done[i], &mut rest[0]);
            for (k, out) in y.iter_mut().enumerate() {
                let row = &layer.weight[k * x.len()..(k + 1) * x.len()];
                let sum: f32 = row.iter().zip(x.iter()).map(|(w, v)| w * v).sum();
                let z = sum + layer.bias[k];
                *out = match (i == last, self.activation) {
                    (true, _) => z,
                    (false, MlpActivation::Tanh) => z.tanh(),
                    (false, MlpActivation::Relu) => z.max(0.0),
                    (false, MlpActivation::Silu) => z / (1.0 + (-z).exp()),
                };
            }
        }
        let y = &self.work[self.layers.len()];
        Ok(std::array::from_fn(|j| match self.output {
            MlpOutput::Clip => y[j].clamp(-1.0, 1.0),
            MlpOutput::Tanh => y[j].tanh(),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_layers(inputs: MlpInputs, obs_dim: usize) -> MlpPolicy {
        let n = obs_dim
            + if inputs == MlpInputs::ScanContext {
                2
            } else {
                0
            };
        let weight = (0..3 * n).map(|i| (i as f32 * 0.37).sin() * 0.2).collect();
        let layers = vec![
            Linear {
                weight,
                bias: vec![0.1, -0.2, 0.05],
            },
            Linear {
                weight: vec![1.0, -2.0, 0.5, 3.0, 0.25, -1.0],
                bias: vec![0.0, 0.1],
            },
        ];
        MlpPolicy::new(
            layers,
            MlpActivation::Tanh,
            inputs,
            MlpOutput::Clip,
            obs_dim,
        )
        .unwrap()
    }

    #[test]
    fn a_policy_file_reads_back_and_acts_as_its_layers_say() {
        let mut p = two_layers(MlpInputs::ScanContext, 4);
        let bytes = p.to_safetensors().unwrap();
        let mut back = MlpPolicy::from_safetensors(&bytes, 4).unwrap();
        assert_eq!(back, p);
        let obs = [0.1, 0.5, 0.9, 0.3];
        let a = p.act(&obs, [0.2, -0.1]).unwrap();
        assert_eq!(back.act(&obs, [0.2, -0.1]).unwrap(), a);
        // by hand: h = tanh(W0 [obs, c] + b0), y = clip(W1 h + b1)
        let x = [0.1f32, 0.5, 0.9, 0.3, 0.2, -0.1];
        let l0 = &p.layers[0];
        let h: Vec<f32> = (0..3)
            .map(|k| {
                let row = &l0.weight[k * 6..(k + 1) * 6];
                (row.iter().zip(&x).map(|(w, v)| w * v).sum::<f32>() + l0.bias[k]).tanh()
            })
            .collect();
        let y0 = (h[0] - 2.0 * h[1] + 0.5 * h[2]).clamp(-1.0, 1.0);
        let y1 = (3.0 * h[0] + 0.25 * h[1] - h[2] + 0.1).clamp(-1.0, 1.0);
        assert!(
            (a[0] - y0).abs() < 1e-6 && (a[1] - y1).abs() < 1e-6,
            "{a:?}"
        );
    }

    #[test]
    fn a_file_that_is_no_mlp_policy_is_refused_naming_what() {
        let p = two_layers(MlpInputs::Scan, 4);
        let bytes = p.to_safetensors().unwrap();
        // another beam count
        let err = MlpPolicy::from_safetensors(&bytes, 5)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("layer 0 takes 4 inputs where 5 arrive"),
            "{err}"
        );
        // not safetensors, or none of this format
        let err = MlpPolicy::from_safetensors(b"nonsense", 4).unwrap_err();
        assert!(err.to_string().contains("not safetensors"), "{err}");
        let plain = safetensors::serialize(
            [(
                "x",
                TensorView::new(Dtype::F32, vec![1], &[0u8; 4]).unwrap(),
            )],
            None,
        )
        .unwrap();
        let err = MlpPolicy::from_safetensors(&plain, 4).unwrap_err();
        assert!(err.to_string().contains(MLP_FORMAT), "{err}");
        // an unknown activation names the choices
        let mut renamed = bytes.clone();
        let at = renamed.windows(6).position(|w| w == b"\"tanh\"").unwrap();
        renamed[at + 1..at + 5].copy_from_slice(b"gelu");
        let err = MlpPolicy::from_safetensors(&renamed, 4).unwrap_err();
        assert!(
            err.to_string()
                .contains("'gelu' is none of tanh, relu, silu"),
            "{err}"
        );
        // a last layer that is no action
        let layers = vec![Linear {
            weight: vec![0.0; 12],
            bias: vec![0.0; 3],
        }];
        let err = MlpPolicy::new(
            layers,
            MlpActivation::Relu,
            MlpInputs::Scan,
            MlpOutput::Tanh,
            4,
        );
        assert!(err.unwrap_err().to_string().contains("gives 3 values"));
    }
}
