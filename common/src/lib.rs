//! What ctxrace processes share: the race context and the experiment configuration types.

pub mod batch;
pub mod config;
pub mod context;
pub mod ipc;
pub mod nn;

pub use batch::{SequenceBatch, TransitionBatch};
pub use config::{ContextGains, LidarConfig, RaceConfig, ReplayOptions, RivalConfig};
pub use context::{Context, ContextError};
