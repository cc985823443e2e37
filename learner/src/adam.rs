//! Adam (Kingma & Ba 2015) with global-norm gradient clipping, on the networks' own tensors, and
//! moments that can be saved (a resumed run continues them).
//!
//! For each parameter `w` with gradient `g`, at step `t` (from 1):
//!
//! ```text
//! g ← g · min(1, clip / ‖G‖)          ‖G‖: the norm of all gradients together
//! m ← β₁ m + (1 − β₁) g,    v ← β₂ v + (1 − β₂) g²
//! w ← w − lr · (m / (1 − β₁ᵗ)) / (√(v / (1 − β₂ᵗ)) + ε)
//! ```
//!
//! (PyTorch's `Adam` without weight decay). The update runs where the network keeps its
//! weights ([`Parameters::update`]), one pass per tensor.

use ctxrace_nn::kernels::{adam_update, sum_of_squares, AdamStep};
use ctxrace_nn::Parameters;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

/// First-moment decay `β₁`.
const BETA1: f64 = 0.9;
/// Second-moment decay `β₂`.
const BETA2: f64 = 0.999;

/// Why an optimiser step or its saved state does not fit the networks it optimises.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AdamError {
    /// A step was given gradients of another set of tensors.
    #[error("the optimiser was given {given} gradients for {tensors} tensors")]
    Gradients {
        /// Gradients given.
        given: usize,
        /// Tensors optimised.
        tensors: usize,
    },
    /// A gradient's length differs from its tensor's.
    #[error("the gradient of '{name}' has {given} values, the tensor {want}")]
    GradientLength {
        /// The tensor's name.
        name: String,
        /// Values in the gradient.
        given: usize,
        /// Values in the tensor.
        want: usize,
    },
    /// The saved state is not of these networks' optimiser.
    #[error("optimiser state: {0}")]
    State(String),
}

/// An Adam optimiser over the tensors of a fixed set of networks.
pub struct Adam {
    /// For each tensor, in the networks' order, its index in the moments' order (by name, group by
    /// group: [`Adam::in_groups`]).
    slots: Vec<usize>,
    /// The tensors' names, in the networks' order.
    names: Vec<String>,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    t: u64,
    lr: f64,
    eps: f64,
    clip: f64,
}

impl Adam {
    /// Adam over the tensors of `nets` with learning rate `lr`, `ε = eps` and the gradient norm
    /// clipped to `clip` (`f64::INFINITY`: no clipping).
    pub fn new<P: Parameters + ?Sized>(nets: &P, lr: f64, eps: f64, clip: f64) -> Self {
        Self::in_groups(nets, &[], lr, eps, clip)
    }

    /// [`Adam::new`] whose moments are ordered group by group, each group's tensors by name: the
    /// tensors of `nets` before index `ends[0]`, then those before `ends[1]`, …, then the rest
    /// (the order of an optimiser over the parameters of several stores, one after the other:
    /// the world model's, over the policy's encoder and RSSM, then the heads).
    pub fn in_groups<P: Parameters + ?Sized>(
        nets: &P,
        ends: &[usize],
        lr: f64,
        eps: f64,
        clip: f64,
    ) -> Self {
        let tensors = nets.tensors();
        let group = |i: usize| ends.iter().filter(|&&end| end <= i).count();
        let key = |i: usize| (group(i), tensors[i].name);
        let mut by_name: Vec<usize> = (0..tensors.len()).collect();
        by_name.sort_by(|&a, &b| key(a).cmp(&key(b)));
        let mut slots = vec![0; tensors.len()];
        for (slot, &i) in by_name.iter().enumerate() {
            slots[i] = slot;
        }
        let zeros = || by_name.iter().map(|&i| vec![0f32; tensors[i].values.len()]);
        Self {
            slots,
            names: tensors.iter().map(|t| t.name.to_string()).collect(),
            m: zeros().collect(),
            v: zeros().collect(),
            t: 0,
            lr,
            eps,
            clip,
        }
    }

    /// Steps taken.
    pub fn steps(&self) -> u64 {
        self.t
    }

    /// One step of `nets` (those this optimiser was made for, in the same order) with `grads`,
    /// one per tensor in their order (an empty one: that tensor has none and is left alone);
    /// returns the gradient norm before clipping. A non-finite norm skips the step, so that
    /// one bad batch cannot poison the weights.
    pub fn step<P: Parameters + ?Sized>(
        &mut self,
        nets: &mut P,
        grads: &[Vec<f32>],
    ) -> Result<f64, AdamError> {
        if grads.len() != self.slots.len() {
            return Err(AdamError::Gradients {
                given: grads.len(),
                tensors: self.slots.len(),
            });
        }
        for (i, g) in grads.iter().enumerate() {
            let want = self.m[self.slots[i]].len();
            if !g.is_empty() && g.len() != want {
                return Err(AdamError::GradientLength {
                    name: self.names[i].clone(),
                    given: g.len(),
                    want,
                });
            }
        }
        // summed in the moments' order, whatever order the networks give their tensors in
        let mut squares = vec![0f64; grads.len()];
        for (g, &slot) in grads.iter().zip(&self.slots) {
            squares[slot] = sum_of_squares(g);
        }
        let norm = squares.iter().sum::<f64>().sqrt();
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
        let coefficients = AdamStep {
            scale,
            beta1: BETA1 as f32,
            beta2: BETA2 as f32,
            lr_t: (self.lr / (1.0 - BETA1.powi(t))) as f32,
            v_corr: (1.0 / (1.0 - BETA2.powi(t))) as f32,
            eps: self.eps as f32,
        };
        let (slots, m, v) = (&self.slots, &mut self.m, &mut self.v);
        let mut failed = None;
        nets.update(&mut |i, w| {
            let (g, slot) = (&grads[i], slots[i]);
            if !g.is_empty() && w.len() == g.len() {
                if let Err(e) = adam_update(w, g, &mut m[slot], &mut v[slot], coefficients) {
                    failed = Some(e.to_string());
                }
            }
        });
        match failed {
            Some(e) => Err(AdamError::State(e)),
            None => Ok(norm),
        }
    }

    /// The moments and step counter as safetensors bytes (`m.{i}`, `v.{i}` for the `i`-th tensor
    /// in the moments' order, and `t`).
    pub fn to_bytes(&self) -> Result<Vec<u8>, AdamError> {
        let as_bytes = |x: &[f32]| x.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>();
        let mut named: Vec<(String, Dtype, Vec<u8>)> = Vec::new();
        for (i, (m, v)) in self.m.iter().zip(&self.v).enumerate() {
            named.push((format!("m.{i}"), Dtype::F32, as_bytes(m)));
            named.push((format!("v.{i}"), Dtype::F32, as_bytes(v)));
        }
        named.push((
            "t".into(),
            Dtype::F64,
            (self.t as f64).to_le_bytes().to_vec(),
        ));
        let views = named
            .iter()
            .map(|(name, dtype, bytes)| {
                let len = 8 * bytes.len() / dtype.bitsize();
                TensorView::new(*dtype, vec![len], bytes)
                    .map(|view| (name.as_str(), view))
                    .map_err(|e| AdamError::State(e.to_string()))
            })
            .collect::<Result<Vec<_>, _>>()?;
        safetensors::serialize(views, None).map_err(|e| AdamError::State(e.to_string()))
    }

    /// Restores what [`Adam::to_bytes`] wrote for the same networks; on an error nothing changes.
    pub fn load_bytes(&mut self, bytes: &[u8]) -> Result<(), AdamError> {
        let file = SafeTensors::deserialize(bytes).map_err(|e| AdamError::State(e.to_string()))?;
        let values = |name: &str, dtype: Dtype| -> Result<Vec<u8>, AdamError> {
            let view = file
                .tensor(name)
                .map_err(|_| AdamError::State(format!("no `{name}`")))?;
            if view.dtype() != dtype {
                return Err(AdamError::State(format!(
                    "`{name}` holds {} values, expected {dtype}",
                    view.dtype()
                )));
            }
            Ok(view.data().to_vec())
        };
        let floats = |name: &str, len: usize| -> Result<Vec<f32>, AdamError> {
            let data = values(name, Dtype::F32)?;
            if data.len() != 4 * len {
                return Err(AdamError::State(format!(
                    "`{name}` has {} values, the parameter {len}",
                    data.len() / 4
                )));
            }
            let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            Ok(data.chunks_exact(4).map(f).collect())
        };
        let tensors = self.m.len();
        if file.len() != 2 * tensors + 1 {
            return Err(AdamError::State(format!(
                "it holds {} tensors, expected {}",
                file.len(),
                2 * tensors + 1
            )));
        }
        let mut m = Vec::with_capacity(tensors);
        let mut v = Vec::with_capacity(tensors);
        for (i, len) in self.m.iter().map(Vec::len).enumerate() {
            m.push(floats(&format!("m.{i}"), len)?);
            v.push(floats(&format!("v.{i}"), len)?);
        }
        let t = match values("t", Dtype::F64)?.as_slice().try_into() {
            Ok(b) => f64::from_le_bytes(b),
            Err(_) => return Err(AdamError::State("`t` is not one value".into())),
        };
        (self.m, self.v, self.t) = (m, v, t as u64);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_nn::NamedTensor;

    /// A vector of weights as a network.
    struct Vector(Vec<f32>);

    impl Parameters for Vector {
        fn tensors(&self) -> Vec<NamedTensor<'_>> {
            vec![NamedTensor {
                name: "w",
                shape: vec![self.0.len()],
                values: &self.0,
            }]
        }

        fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
            f(0, &mut self.0);
        }
    }

    #[test]
    fn first_step_moves_each_weight_by_lr_against_its_gradient_sign() {
        // at t = 1, m̂ = g and v̂ = g², so Δw = −lr g / (|g| + ε)
        let mut w = Vector(vec![1.0, -2.0, 0.5]);
        let mut adam = Adam::new(&w, 0.1, 1e-8, f64::INFINITY);
        let norm = adam.step(&mut w, &[vec![3.0, -1.0, 0.0]]).unwrap();
        assert!((norm - 10f64.sqrt()).abs() < 1e-6);
        for (a, e) in w.0.iter().zip([0.9f32, -1.9, 0.5]) {
            assert!((a - e).abs() < 1e-6, "{:?}", w.0);
        }
        // no gradient: left alone, and the step still counts
        adam.step(&mut w, &[vec![]]).unwrap();
        assert_eq!((adam.steps(), w.0[2]), (2, 0.5));
    }

    #[test]
    fn clipping_scales_the_gradient_and_state_round_trips() {
        let mut w = Vector(vec![0.0, 0.0]);
        let mut adam = Adam::new(&w, 0.01, 1e-8, 1.0);
        let grad = |w: &Vector| vec![vec![2.0 * (w.0[0] - 3.0), 2.0 * (w.0[1] - 4.0)]];
        // gradient −2·(3, 4), norm 10, clipped to 1: m = 0.1 · (−0.6, −0.8)
        let g = grad(&w);
        assert!((adam.step(&mut w, &g).unwrap() - 10.0).abs() < 1e-5);
        assert!((adam.m[0][0] + 0.06).abs() < 1e-7 && (adam.m[0][1] + 0.08).abs() < 1e-7);
        for _ in 0..3 {
            let g = grad(&w);
            adam.step(&mut w, &g).unwrap();
        }
        let bytes = adam.to_bytes().unwrap();
        let mut other = Adam::new(&w, 0.01, 1e-8, 1.0);
        other.load_bytes(&bytes).unwrap();
        assert_eq!(
            (other.m.clone(), other.v.clone(), other.t),
            (adam.m.clone(), adam.v.clone(), 4)
        );
        let mut wrong = Adam::new(&Vector(vec![0.0; 3]), 0.01, 1e-8, 1.0);
        let err = wrong.load_bytes(&bytes).unwrap_err().to_string();
        assert!(err.contains('3'), "{err}");
        assert!(matches!(
            adam.step(&mut w, &[vec![1.0; 3]]),
            Err(AdamError::GradientLength { .. })
        ));
        assert!(matches!(
            adam.step(&mut w, &[]),
            Err(AdamError::Gradients { .. })
        ));
    }

    /// A named vector of weights as a network.
    struct Named(&'static str, Vec<f32>);

    impl Parameters for Named {
        fn tensors(&self) -> Vec<NamedTensor<'_>> {
            vec![NamedTensor {
                name: self.0,
                shape: vec![self.1.len()],
                values: &self.1,
            }]
        }

        fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
            f(0, &mut self.1);
        }
    }

    #[test]
    fn moments_are_ordered_by_name_within_each_group() {
        let (mut z, mut y, mut a) = (
            Named("z", vec![0.0]),
            Named("y", vec![0.0; 2]),
            Named("a", vec![0.0; 3]),
        );
        let nets: &mut [&mut dyn Parameters] = &mut [&mut z, &mut y, &mut a];
        let lengths = |adam: &Adam| adam.m.iter().map(Vec::len).collect::<Vec<_>>();
        assert_eq!(lengths(&Adam::new(nets, 0.1, 1e-8, 1.0)), [3, 2, 1]);
        let mut grouped = Adam::in_groups(nets, &[2], 0.1, 1e-8, 1.0);
        assert_eq!(lengths(&grouped), [2, 1, 3]);
        // each gradient still reaches its own tensor
        let grads = [vec![1.0], vec![0.0, 2.0], vec![0.0; 3]];
        grouped.step(nets, &grads).unwrap();
        assert_eq!(
            (z.1[0] < 0.0, y.1[0], y.1[1] < 0.0, a.1),
            (true, 0.0, true, vec![0.0; 3])
        );
    }
}
