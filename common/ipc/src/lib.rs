//! Shared-memory transport between a run's processes (iceoryx2 0.10).
//!
//! | service | pattern | from -> to |
//! | --- | --- | --- |
//! | `trajectory/<actor>` | `[f32]` chunks + [`ChunkHeader`], no overflow, one per actor | actor -> replay |
//! | `batch_request`, `batch` | [`BatchRequest`]; `[f32]` + [`BatchHeader`] | learner <-> replay |
//! | `weights` | `[u8]` + [`WeightsHeader`], history 1 | learner -> actors |
//! | `metrics`, `heartbeat`, `replay_status` | plain structs | actors, replay -> launcher |
//! | `wake_*`, `replay_ready` | events | whoever must wake up |
//!
//! Every process opens a [`RunTransport`] with the run's prefix ([`run_prefix`]); services of
//! other prefixes are invisible. Senders wait for the replay's `replay_ready` event before their
//! first chunk (a chunk sent before a subscriber connected is silently lost); a chunk the
//! replay has no room for waits in its sender's backlog (the actor pauses) and is dropped, and
//! counted, only if it is still waiting when the sender closes
//! ([`SenderOptions::close_timeout`]). The replay takes the actors' queues in turn. Management
//! files live in the user's private [`shm_root`]; [`cleanup`] removes the run's dead nodes and
//! shared-memory files, and [`sweep_orphaned_runs`] those of runs whose launcher died.

mod batches;
pub mod bounds;
mod error;
pub mod inject;
mod key;
mod shared;
mod telemetry;
mod trajectory;
mod transport;
mod weights;
pub mod wire;

pub use batches::{BatchServer, ReplayClient, RESEND_AFTER};
pub use bounds::RunBounds;
pub use ctxrace_config::config::DEFAULT_MAX_BATCH_FLOATS;
pub use ctxrace_run::steps::TrajectoryStep;
pub use error::IpcError;
pub use error::SHM_ROOT_ENV;
pub use key::{KeyPipe, RunKey, KEY_FD_FLAG, KEY_LEN};
pub use telemetry::{EpisodeSubscriber, MetricsPublisher, StatusPublisher, TelemetrySubscriber};
pub use trajectory::{
    ChunkView, ReplayBeacon, SenderOptions, SenderStats, TrajectoryReceiver, TrajectorySender,
};
pub use transport::{
    claim_run, cleanup, iceoryx_config, remove_dead_nodes, run_prefix, shm_root,
    sweep_orphaned_runs, termination_flag, CleanupReport, Next, RunTransport, Sweep, Wake,
    TRAJECTORY_BUFFER,
};
pub use weights::{WeightsPublisher, WeightsReceiver, DEFAULT_MAX_WEIGHTS_BYTES};

/// Where a reader of shared memory stands with one message. Readers copy a message out of
/// shared memory, validate the copy and use only the copy; their `*_observed` variants call a
/// hook at each stage, so that a fault-injection test can rewrite the message in shared memory
/// (see [`inject::Held`]) at exactly that point and show that it makes no difference.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadStage {
    /// The message was copied out of shared memory; the copy is not validated yet.
    Copied,
    /// The copy was validated; it is not used yet.
    Validated,
}

pub use wire::{
    BatchHeader, BatchRequest, ChunkHeader, EpisodeReport, Heartbeat, ReplayStatus, WeightsHeader,
    WireError,
};

/// Counts rejected messages by reason ([`wire::REASONS`]) and logs them: the first ten, then
/// every thousandth, so a flood of bad input cannot flood the log.
pub(crate) struct RejectLog {
    what: &'static str,
    by_reason: [u64; wire::REASONS.len()],
}

impl RejectLog {
    pub(crate) fn new(what: &'static str) -> Self {
        Self {
            what,
            by_reason: [0; wire::REASONS.len()],
        }
    }

    pub(crate) fn reject(&mut self, error: &WireError) {
        self.note(error.reason(), error);
    }

    /// Counts a rejection under the reason of index `reason` ([`wire::REASONS`]), `why` saying
    /// what it was.
    pub(crate) fn note(&mut self, reason: usize, why: &dyn std::fmt::Display) {
        self.by_reason[reason] += 1;
        let count = self.count();
        if count <= 10 || count.is_multiple_of(1000) {
            tracing::warn!("rejected {} ({count} so far): {why}", self.what);
        }
    }

    pub(crate) fn count(&self) -> u64 {
        self.by_reason.iter().sum()
    }

    pub(crate) fn by_reason(&self) -> [u64; wire::REASONS.len()] {
        self.by_reason
    }
}

/// The key of the tests' runs.
#[cfg(test)]
pub(crate) fn test_key() -> RunKey {
    RunKey::from_bytes([9; KEY_LEN])
}

/// A test's own run prefix, removed even when the test panics.
#[cfg(test)]
pub(crate) struct Isolated(pub(crate) String);

#[cfg(test)]
impl Isolated {
    /// The prefix `test-<name>-<pid>`.
    pub(crate) fn new(name: &str) -> Self {
        Self(run_prefix(&format!("test-{name}-{}", std::process::id())))
    }
}

#[cfg(test)]
impl Drop for Isolated {
    fn drop(&mut self) {
        let _ = cleanup(&self.0);
    }
}
