//! The learner's one error type: what went wrong building an agent or taking a training step.

use crate::adam::AdamError;
use crate::checkpoint::CheckpointError;
use ctxrace_config::agents::AgentConfigError;
use ctxrace_config::BatchError;
use ctxrace_nn::policy::PolicyError;
use ctxrace_nn::WeightsError;

/// Why an agent could not be built, trained or serialised.
#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    /// The agent's configuration is invalid (its message names the key).
    #[error("agent config")]
    Config(#[from] AgentConfigError),
    /// A DreamerV3 agent without observations or actions.
    #[error("agent config: DreamerV3 needs observations and actions (sizes {obs}, {action})")]
    Sizes {
        /// Observation size.
        obs: usize,
        /// Action size.
        action: usize,
    },
    /// cMask's mask SAC with a temperature that is not positive.
    #[error("agent config: agent.dreamer.mask.init_alpha = {0} must be positive")]
    MaskTemperature(f64),
    /// A batch that does not fit the agent (its sizes, or values out of range).
    #[error("batch")]
    Batch(#[from] BatchError),
    /// DreamerV3 was given transitions.
    #[error("batch: DreamerV3 trains on sequence batches, not transitions")]
    Transitions,
    /// A world-model step on a batch of no sequences.
    #[error("batch: world model: a batch of no sequences")]
    NoSequences,
    /// A behaviour step with no imagined state to learn from.
    #[error("batch: behaviour learning: no imagined states")]
    NoImaginedStates,
    /// The acting policy could not be built from the agent's weights.
    #[error(transparent)]
    Policy(#[from] PolicyError),
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

/// Why a SAC agent could not be built, stepped, saved or restored.
#[derive(Debug, thiserror::Error)]
pub enum SacError {
    /// A network size is zero.
    #[error(
        "SAC needs positive sizes, got observation {obs}, action {action}, hidden {hidden} \
         (agent.sac.hidden must be positive)"
    )]
    Sizes {
        /// Observation size.
        obs: usize,
        /// Action size.
        action: usize,
        /// Hidden units.
        hidden: usize,
    },
    /// The observation is not a whole number of stacked frames.
    #[error("SAC observation size {obs} is not a multiple of agent.sac.frames = {frames}")]
    Frames {
        /// Observation size.
        obs: usize,
        /// Frames stacked.
        frames: usize,
    },
    /// The configuration is invalid (the message names the key).
    #[error(transparent)]
    Config(#[from] AgentConfigError),
    /// A batch does not fit the agent.
    #[error(transparent)]
    Batch(#[from] BatchError),
    /// The mask SAC's batch could not be split over its workers (or a worker panicked).
    #[error("the mask SAC's shards")]
    Shards(#[source] Box<LearnerError>),
    /// The mask SAC's batch has no valid transition to split.
    #[error("the mask SAC's batch has no shards")]
    NoShards,
    /// SAC was given sequences.
    #[error("SAC trains on transitions, not sequences")]
    Sequences,
    /// An optimiser's step or state.
    #[error(transparent)]
    Optimiser(#[from] AdamError),
    /// Weights that do not fit the networks.
    #[error(transparent)]
    Weights(#[from] WeightsError),
}
