//! The replay process of a ctxrace run: a ring buffer of the actors' steps, a samples-per-insert
//! rate limiter, snapshots, and the process loop serving the learner.

pub mod buffer;
pub mod limiter;
pub mod numpy_rng;
pub mod server;
pub mod snapshot;
mod store;

pub use buffer::ReplayBuffer;
pub use limiter::RateLimiter;
pub use server::{check_restorable, run, ReplayArgs, ReplayControl, ReplayError};
pub use snapshot::{
    encode_snapshot, read_snapshot, write_encoded, write_snapshot, BackgroundWriter, LimiterCounts,
    SnapshotDamage, SnapshotError, SnapshotShape,
};
