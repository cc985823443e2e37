//! The networks shared by acting and training (plain buffers, CPU, f32); candle's modules and
//! custom ops are the tests' oracle only (`cfg(test)` or the `oracle` feature).

#[cfg(any(test, feature = "oracle"))]
pub mod dense;
pub mod dreamer;
pub mod initial_weights;
pub mod kernels;
pub mod mlp;
#[cfg(any(test, feature = "oracle"))]
pub mod norm;
#[cfg(any(test, feature = "oracle"))]
pub mod params;
pub mod plain;
pub mod rssm;
pub mod symlog;
pub mod tanh_gaussian;
pub mod weights;

pub use kernels::NormAct;
pub use mlp::{Activation, MlpShape};
pub use rssm::RssmConfig;
pub use symlog::{symlog_value, TwoHot};
pub use weights::{Weights, WeightsError};

// candle's modules: the tests' oracle (`oracle` feature)
#[cfg(any(test, feature = "oracle"))]
pub use dense::Dense;
#[cfg(any(test, feature = "oracle"))]
pub use mlp::{HiddenBlock, Mlp};
#[cfg(any(test, feature = "oracle"))]
pub use norm::LayerNorm;
#[cfg(any(test, feature = "oracle"))]
pub use params::ParamStore;
#[cfg(any(test, feature = "oracle"))]
pub use rssm::{Gru, Rssm, RssmState};
#[cfg(any(test, feature = "oracle"))]
pub use symlog::symlog;
#[cfg(any(test, feature = "oracle"))]
pub use tanh_gaussian::TanhGaussianActor;

/// Makes candle's own kernels run on the calling thread, for the tests' candle oracles (no
/// production code runs candle: the networks, the learner's and the actors', run the plain
/// passes on gemm without its thread pool). The learner splits a batch over the worker threads
/// it is given instead; candle's threads spin against them on small products, and unset,
/// candle re-derives its thread count on every product. candle reads these settings from the
/// environment only, so this sets `RAYON_NUM_THREADS` and `CANDLE_NUM_THREADS`.
#[cfg(any(test, feature = "oracle"))]
pub fn candle_on_one_thread() {
    std::env::set_var("RAYON_NUM_THREADS", "1");
    std::env::set_var("CANDLE_NUM_THREADS", "1");
}
