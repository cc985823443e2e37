//! The learner's one error type: what went wrong building an agent or taking a training step.

use crate::adam::AdamError;
use crate::checkpoint::CheckpointError;
use crate::sac_core::SacError;
use ctxrace_nn::WeightsError;

/// Why an agent could not be built, trained or serialised.
#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    /// The agent's configuration is invalid (the message names the key).
    #[error("agent config: {0}")]
    Config(String),
    /// A batch the algorithm cannot train on: what is wrong with it.
    #[error("batch: {0}")]
    Batch(String),
    /// A network's weights could not be built, read or written.
    #[error(transparent)]
    Weights(#[from] WeightsError),
    /// An optimiser step or its state failed.
    #[error(transparent)]
    Optimiser(#[from] AdamError),
    /// SAC (or cMask's mask SAC) failed.
    #[error(transparent)]
    Sac(#[from] SacError),
    /// A checkpoint could not be written or read.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// A training step's per-shard inputs do not cover its shards (one worker state a shard,
    /// one noise stream a sequence): a caller's error, reported instead of a panic.
    #[error(
        "a training step over {batch} sequences in {shards} shards was given {states} worker \
         states and {streams} noise streams (one state a shard, one stream a sequence)"
    )]
    ShardInputs {
        /// Sequences in the batch.
        batch: usize,
        /// Shards the batch is split into.
        shards: usize,
        /// Worker states given.
        states: usize,
        /// Noise streams given.
        streams: usize,
    },
    /// A worker thread of a training step panicked.
    #[error("a training worker thread panicked")]
    WorkerPanicked,
}

/// The outcome of a learner operation.
pub type Result<T> = std::result::Result<T, LearnerError>;
