//! What ctxrace processes share: the race context, the experiment configuration types, the
//! neural-network modules and the acting policies, run-directory names and result rows, and the
//! traits a single-process trainer runs on (`experience`).

pub mod agents;
pub mod batch;
pub mod config;
pub mod context;
pub mod experience;
pub mod experiment;
pub mod ipc;
pub mod nn;
pub mod policy;
pub mod preset;
pub mod results;
pub mod run_dir;
pub mod validate;

pub use agents::{
    AgentConfig, AgentPreset, AlgoKind, ContextMode, ContextScale, DreamerConfig, MaskConfig,
    SacConfig, Sampler, Warmup,
};
pub use batch::{Batch, BatchError, BatchSpec, SequenceBatch, TransitionBatch};
pub use config::{
    ContextGains, CrashedRivals, GridLine, Integrator, LidarConfig, RaceConfig, RaceConfigError,
    RacePreset, ReplayOptions, RivalConfig, SpeedPoint, StartGrid, WallContact,
};
pub use context::{Context, ContextError};
pub use experiment::{ExperimentConfig, ExperimentError, SupervisorConfig, TrainConfig};
pub use policy::{Decision, Policy};
