//! The tests' oracle: the networks of ctxrace-nn as candle modules, which every hand-written
//! forward and backward pass is checked against, values and gradients, and those checks (the
//! tests of this crate). A dev-dependency only (of the learner's tests; `publish = false`): no
//! production code runs candle, and `cargo tree -p ctxrace -e normal` has no candle.
//!
//! - [`kernels`]: the candle custom ops around ctxrace-nn's row kernels.
//! - [`Dense`], [`LayerNorm`]: a linear layer and a normalisation on those ops, with candle-nn's
//!   parameter names.
//! - [`Mlp`], [`Rssm`] (with [`Gru`], [`RssmState`], [`standalone`]), [`TanhGaussianActor`]
//!   (with [`squash`]), [`DreamerNets`]: the networks.
//! - [`ParamStore`]: the named, seeded variables the modules are built in; they write the
//!   safetensors names the networks read ([`ctxrace_nn::Weights`]).
//! - [`symlog`] and [`TwoHotTensors`]: `TwoHot`'s `encode`, `decode` and `loss` on tensors.
//! - The bridge ([`bridge`]): a network copied from its candle module ([`FromOracle`]), and its
//!   gradients handed back keyed by the module's tensors ([`AddGradsTo`]).

pub mod bridge;
mod dense;
pub mod dreamer;
pub mod kernels;
mod mlp;
mod norm;
mod params;
mod rssm;
mod symlog;
mod tanh_gaussian;
#[cfg(test)]
mod testing;
#[cfg(test)]
mod tests;

pub use bridge::{AddGradsTo, FromOracle};
pub use dense::Dense;
pub use dreamer::DreamerNets;
pub use mlp::{HiddenBlock, Mlp};
pub use norm::LayerNorm;
pub use params::ParamStore;
pub use rssm::{standalone, Gru, Rssm, RssmState};
pub use symlog::{symlog, TwoHotTensors};
pub use tanh_gaussian::{squash, TanhGaussianActor};

/// Makes candle's own kernels run on the calling thread, for the tests' candle oracles (no
/// production code runs candle: the networks, the learner's and the actors', run the
/// hand-written passes on gemm without its thread pool). The learner splits a batch over the
/// worker threads it is given instead; candle's threads spin against them on small products,
/// and unset, candle re-derives its thread count on every product. candle reads these settings
/// from the environment only, so this sets `RAYON_NUM_THREADS` and `CANDLE_NUM_THREADS`.
pub fn candle_on_one_thread() {
    std::env::set_var("RAYON_NUM_THREADS", "1");
    std::env::set_var("CANDLE_NUM_THREADS", "1");
}
