//! Neural-network modules shared by acting and training (candle, CPU, f32).

pub mod dense;
pub mod kernels;
pub mod mlp;
pub mod norm;
pub mod params;
pub mod rssm;
pub mod symlog;
pub mod tanh_gaussian;

pub use dense::Dense;
pub use kernels::NormAct;
pub use mlp::{Activation, Mlp};
pub use norm::LayerNorm;
pub use params::ParamStore;
pub use rssm::{Gru, Rssm, RssmConfig, RssmState};
pub use symlog::{symexp, symlog, TwoHot};
pub use tanh_gaussian::TanhGaussianActor;

/// Sets the number of threads candle's CPU kernels use. Unset, candle re-derives it on every
/// matrix product, which is several times slower at batch 1; call once at start-up.
pub fn set_threads(n: usize) {
    // candle reads RAYON_NUM_THREADS on every product; call before other threads start
    std::env::set_var("RAYON_NUM_THREADS", n.max(1).to_string());
}
