//! ctxrace's configuration: the experiment (track, race, agent, training, replay, supervisor),
//! what its run is held to (its plan), the race context, presets, the shapes of training batches, and the checks that refuse a bad
//! value by its key. It knows neither the transport nor the networks: the crates that do read
//! their sizes and bounds from here.

pub mod agents;
pub mod batch;
pub mod config;
pub mod config_file;
pub mod context;
pub mod experiment;
pub mod plan;
pub mod preset;
pub mod replay;
pub mod resources;
pub mod rival;
pub mod validate;

pub use agents::{
    AgentConfig, AgentPreset, AlgoKind, ContextMode, ContextScale, DreamerConfig, MaskConfig,
    SacConfig, Sampler, Warmup,
};
pub use batch::{Batch, BatchError, BatchSpec, SequenceBatch, TransitionBatch};
pub use config::{
    CrashedRivals, GridLine, Integrator, LidarConfig, RaceConfig, RaceConfigError, RacePreset,
    RivalContacts, StartGrid, WallContact, MAX_OBS, MAX_RIVALS,
};
pub use context::{Context, ContextError};
pub use experiment::{ExperimentConfig, ExperimentError, SupervisorConfig, TrainConfig};
pub use plan::RunPlan;
pub use replay::ReplayOptions;
pub use rival::{
    ContextGains, FollowTheGapConfig, GapAim, RivalConfig, RivalDriverKind, SpeedPoint,
};
