//! What ctxrace processes share: the race context and the experiment configuration types.

pub mod config;
pub mod context;

pub use config::{ContextGains, LidarConfig, RaceConfig, RivalConfig};
pub use context::{Context, ContextError};
