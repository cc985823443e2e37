//! The interface every training algorithm implements, so that the inline trainer and the learner
//! process can drive any of them by name.

use crate::checkpoint::CheckpointError;
use crate::error::Result;
pub use ctxrace_config::batch::Batch;
use std::collections::BTreeMap;
use std::path::Path;

/// Scalars reported by a training step (losses, entropies, …), by name.
pub type Metrics = BTreeMap<String, f64>;

/// A training algorithm.
pub trait Algorithm {
    /// One gradient step on `batch`; returns its metrics.
    fn train_step(&mut self, batch: &Batch) -> Result<Metrics>;
    /// The acting policy's weights as safetensors bytes.
    fn policy_weights(&self) -> Result<Vec<u8>>;
    /// Writes every weight, optimiser state and counter into `dir`.
    fn save(&self, dir: &Path) -> std::result::Result<(), CheckpointError>;
    /// Restores what [`Algorithm::save`] wrote.
    fn load(&mut self, dir: &Path) -> std::result::Result<(), CheckpointError>;
    /// Training steps taken.
    fn steps(&self) -> u64;
    /// Computes the step's costly diagnostics (cMask's `mask/q_spread`) only on the steps whose
    /// count after the step is a multiple of `every`: the steps whose metrics are logged
    /// (`[train] log_every`). By default, and for an algorithm without such diagnostics, every
    /// step reports every metric.
    fn set_diagnostics_every(&mut self, every: u64) {
        let _ = every;
    }
}

/// The value of a one-element candle tensor (the tests' oracle), for [`Metrics`].
#[cfg(test)]
pub(crate) fn scalar(t: &candle_core::Tensor) -> candle_core::Result<f64> {
    Ok(t.to_dtype(candle_core::DType::F32)?.to_scalar::<f32>()? as f64)
}
