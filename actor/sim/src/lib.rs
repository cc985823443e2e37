//! The ctxrace simulator, a library that needs no transport: the f1tenth single-track vehicle,
//! an exact LiDAR, exact collisions, rivals scaled by the context (pure pursuit on the
//! raceline, follow-the-gap on their own scan: [`gap`], or a trained agent: [`policy_rival`],
//! the one use of the networks here), the head-to-head
//! [`RaceEnv`], many of them stepped together on worker threads ([`vector`]), reference egos,
//! the paper's evaluation protocol ([`evaluation`]) and the episode loop of any ego ([`driver`]).

pub mod baseline;
pub mod collision;
pub mod driver;
pub mod eval_dir;
pub mod evaluation;
pub mod gap;
pub mod grid;
pub mod lidar;
pub mod masks;
pub mod policy_rival;
pub mod race;
pub mod rival;
pub mod scenario;
pub mod track_check;
pub mod vector;
pub mod vehicle;

pub use race::{AgentStep, EpisodeMetrics, RaceEnv, RaceError, Step, StepInfo};
