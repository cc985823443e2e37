//! Neural-network modules shared by acting and training (candle, CPU, f32).

pub mod dense;
pub mod kernels;
pub mod mlp;
pub mod norm;
pub mod params;
pub mod plain;
pub mod rssm;
pub mod symlog;
pub mod tanh_gaussian;

pub use dense::Dense;
pub use kernels::NormAct;
pub use mlp::{Activation, HiddenBlock, Mlp};
pub use norm::LayerNorm;
pub use params::ParamStore;
pub use rssm::{Gru, Rssm, RssmConfig, RssmState};
pub use symlog::{symexp, symlog, TwoHot};
pub use tanh_gaussian::TanhGaussianActor;

/// Worker threads of the learner, set by [`set_threads`].
static WORKERS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(1);

/// Sets the learner's parallelism to `n` worker threads. DreamerV3 splits each batch over them
/// (every worker runs the forward and backward passes of its sequences and the gradients are
/// summed), which on two cores is twice as fast as splitting each tensor operation: those are
/// small and memory-bound, and their threads spin against each other. candle's own kernels
/// therefore run on one thread (unset, candle re-derives its thread count on every matrix
/// product, which is several times slower at batch 1). Call once at start-up, before other
/// threads start.
pub fn set_threads(n: usize) {
    WORKERS.store(n.max(1), std::sync::atomic::Ordering::Relaxed);
    // candle reads RAYON_NUM_THREADS on every product, CANDLE_NUM_THREADS once for the pool of
    // its elementwise kernels (whose workers would spin beside the learner's)
    std::env::set_var("RAYON_NUM_THREADS", "1");
    std::env::set_var("CANDLE_NUM_THREADS", "1");
}

/// The learner's worker threads (see [`set_threads`]).
pub fn threads() -> usize {
    WORKERS.load(std::sync::atomic::Ordering::Relaxed)
}
