//! Neural-network modules shared by acting and training (candle, CPU, f32).

pub mod dense;
pub mod dreamer;
pub mod initial_weights;
pub mod kernels;
pub mod mlp;
pub mod norm;
pub mod params;
pub mod plain;
pub mod rssm;
pub mod symlog;
pub mod tanh_gaussian;
pub mod weights;

pub use dense::Dense;
pub use kernels::NormAct;
pub use mlp::{Activation, HiddenBlock, Mlp, MlpShape};
pub use norm::LayerNorm;
pub use params::ParamStore;
pub use rssm::{Gru, Rssm, RssmConfig, RssmState};
pub use symlog::{symexp, symlog, symlog_value, TwoHot};
pub use tanh_gaussian::TanhGaussianActor;
pub use weights::{Weights, WeightsError};

/// Makes candle's own kernels run on the calling thread. The learner parallelises over the
/// batch instead (DreamerV3 splits each batch over its workers, see
/// `ctxrace_learner::build`), which on two cores is twice as fast as splitting each tensor
/// operation: those are small and memory-bound, and their threads spin against each other; and
/// unset, candle re-derives its thread count on every matrix product, which is several times
/// slower at batch 1. candle reads these settings from the environment only, so this sets
/// `RAYON_NUM_THREADS` (read on every product) and `CANDLE_NUM_THREADS` (read once, for the pool
/// of its elementwise kernels). Call once at start-up, before other threads start.
pub fn candle_on_one_thread() {
    std::env::set_var("RAYON_NUM_THREADS", "1");
    std::env::set_var("CANDLE_NUM_THREADS", "1");
}
