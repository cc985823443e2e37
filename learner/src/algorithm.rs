//! The interface every training algorithm implements, so that the inline trainer and the learner
//! process can drive any of them by name.

use candle_core::Result;
use ctxrace_common::{SequenceBatch, TransitionBatch};
use std::collections::BTreeMap;
use std::path::Path;

/// Scalars reported by a training step (losses, entropies, …), by name.
pub type Metrics = BTreeMap<String, f64>;

/// A training batch of either kind.
#[derive(Clone, Debug)]
pub enum Batch {
    /// Independent transitions (SAC).
    Transitions(TransitionBatch),
    /// Sequences (DreamerV3 and its context-aware variants).
    Sequences(SequenceBatch),
}

/// Which kind of batch an algorithm trains on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BatchKind {
    /// [`Batch::Transitions`].
    Transitions,
    /// [`Batch::Sequences`].
    Sequences,
}

/// A training algorithm.
pub trait Algorithm {
    /// The kind of batch [`Algorithm::train_step`] expects.
    fn batch_kind(&self) -> BatchKind;
    /// One gradient step on `batch`; returns its metrics.
    fn train_step(&mut self, batch: &Batch) -> Result<Metrics>;
    /// The acting policy's weights as safetensors bytes.
    fn policy_weights(&self) -> Result<Vec<u8>>;
    /// Writes every weight, optimiser state and counter into `dir`.
    fn save(&self, dir: &Path) -> Result<()>;
    /// Restores what [`Algorithm::save`] wrote.
    fn load(&mut self, dir: &Path) -> Result<()>;
    /// Training steps taken.
    fn steps(&self) -> u64;
}
