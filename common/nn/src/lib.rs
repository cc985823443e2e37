//! ctxrace's networks, shared by acting and training, on plain row-major `f32` buffers (CPU),
//! differentiated by hand, and the acting policies the actors run ([`policy`]). No candle: the
//! same networks as candle modules, which every hand-written pass is checked against, are the
//! tests' oracle, the dev-only crate `ctxrace-oracle`.
//!
//! - [`layer`]: a layer and an MLP ([`Layer`], [`Mlp`]), their traces and gradients.
//! - [`rssm`]: DreamerV3's RSSM with the cRSSM context ([`Rssm`]).
//! - [`dreamer`]: the networks that act ([`dreamer::PolicyNets`]), the heads on the model state,
//!   the noise both the learner and the actors draw.
//! - [`tanh_gaussian`]: SAC's squashed Gaussian on rows; [`symlog`]: symlog and the two-hot
//!   targets; [`losses`]: the row losses (two-hot decoding, cross-entropy, categorical KL).
//! - [`parameters`]: the trainable tensors where the networks keep them (visited by name: seeded
//!   draws, safetensors, Polyak); [`weights`]: tensors read by name from safetensors;
//!   [`initial_weights`]: which draw each DreamerV3 tensor takes.
//! - [`kernels`]: the fused row kernels and gemm products the passes run on.
//! - [`policy`]: the acting policies (SAC, the DreamerV3 family) on these networks.

pub mod dreamer;
pub mod initial_weights;
pub mod kernels;
pub mod layer;
pub mod losses;
pub mod parameters;
pub mod policy;
pub mod rssm;
pub mod symlog;
pub mod tanh_gaussian;
pub mod weights;

pub use kernels::NormAct;
pub use layer::{
    Activation, InputGrad, Layer, LayerGrads, Mlp, MlpGrads, MlpShape, MlpTrace, NonZeros, Rows,
};
pub use parameters::{NamedTensor, Parameters};
pub use policy::{Decision, Policy};
pub use rssm::{ObserveTrace, Rssm, RssmConfig, RssmGrads, StepScratch, StepTrace};
pub use symlog::{symlog_value, TwoHot};
pub use weights::{Weights, WeightsError};

/// The logistic function `σ(x) = 1 / (1 + e^{−x})`, as the acting policies and the learner's
/// passes compute it (the fused kernels keep their own vectorisable form of `e^{−x}`).
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `v` resized to `n` values (zeros where it grows) as a slice: a scratch buffer kept from one
/// pass to the next, sized for this one.
pub fn sized(v: &mut Vec<f32>, n: usize) -> &mut [f32] {
    v.resize(n, 0.0);
    &mut v[..n]
}
