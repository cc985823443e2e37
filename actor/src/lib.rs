//! The ctxrace simulator: the f1tenth single-track vehicle, an exact LiDAR, exact collisions,
//! pure-pursuit rivals scaled by the context, the head-to-head [`RaceEnv`], the paper's
//! evaluation protocol ([`evaluation`]) and the episodes' driver ([`driver`]).

pub mod baseline;
pub mod collect;
pub mod collision;
pub mod driver;
pub mod evaluation;
pub mod grid;
pub mod lidar;
pub mod process;
pub mod race;
pub mod rival;
pub mod vehicle;

pub use race::{EpisodeMetrics, RaceEnv, RaceError, Step, StepInfo};
