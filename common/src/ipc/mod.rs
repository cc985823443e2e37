//! Shared-memory transport between a run's processes (iceoryx2 0.10).
//!
//! | service | pattern | from -> to |
//! | --- | --- | --- |
//! | `trajectory` | `[f32]` chunks + [`ChunkHeader`], no overflow | actors -> replay |
//! | `batch_request`, `batch` | [`BatchRequest`]; `[f32]` + [`BatchHeader`] | learner <-> replay |
//! | `weights` | `[u8]` + [`WeightsHeader`], history 1 | learner -> actors |
//! | `metrics`, `heartbeat`, `replay_status` | plain structs | actors, replay -> launcher |
//! | `wake_*`, `replay_ready` | events | whoever must wake up |
//!
//! Every process opens a [`RunTransport`] with the run's prefix ([`run_prefix`]); services of
//! other prefixes are invisible. Senders wait for the replay's `replay_ready` event before their
//! first chunk (a chunk sent before a subscriber connected is silently lost); a full replay
//! holds a sender back for at most [`SenderOptions::backpressure_timeout`], then the chunk is
//! dropped and counted. [`cleanup`] removes the run's dead nodes and shared-memory files.

mod batches;
mod telemetry;
mod trajectory;
mod transport;
mod weights;
pub mod wire;

pub use batches::{Batch, BatchServer, BatchSpec, ReplayClient, DEFAULT_MAX_BATCH_FLOATS};
pub use telemetry::{EpisodeSubscriber, MetricsPublisher, StatusPublisher, TelemetrySubscriber};
pub use trajectory::{
    ChunkView, ReplayBeacon, SenderOptions, SenderStats, Step, TrajectoryReceiver, TrajectorySender,
};
pub use transport::{
    cleanup, iceoryx_config, run_prefix, termination_flag, CleanupReport, RunTransport, Wake,
    TRAJECTORY_BUFFER,
};
pub use weights::{WeightsPublisher, WeightsReceiver, DEFAULT_MAX_WEIGHTS_BYTES};
pub use wire::{
    BatchHeader, BatchRequest, ChunkHeader, EpisodeMetrics, Heartbeat, ReplayStatus, WeightsHeader,
    WireError,
};

/// Counts rejected messages and logs them: the first ten, then every thousandth, so a flood of
/// bad input cannot flood the log.
pub(crate) struct RejectLog {
    what: &'static str,
    count: u64,
}

impl RejectLog {
    pub(crate) fn new(what: &'static str) -> Self {
        Self { what, count: 0 }
    }

    pub(crate) fn reject(&mut self, error: &WireError) {
        self.count += 1;
        if self.count <= 10 || self.count.is_multiple_of(1000) {
            tracing::warn!("rejected {} ({} so far): {error}", self.what, self.count);
        }
    }

    pub(crate) fn count(&self) -> u64 {
        self.count
    }
}
