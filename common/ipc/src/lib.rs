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
//!
//! # Authentication and threat model
//!
//! Every message carries a CRC-32 and a 32-byte BLAKE3 tag keyed with the run's [`RunKey`]
//! over all its other fields and its payload ([`wire::Sealer`]); readers check the version, the
//! checksum (`checksum`: an accident), the tag (`unauthenticated`: a message no holder of the
//! key made), then everything else, and a message rejected for any reason changes no reader's
//! state, only its counters. The launcher draws the key from the OS random source at each launch
//! (a resumed run gets a new one) and hands it to each start of each child over a pipe of its own
//! ([`RunKey::hand_to`]); it is never in a command line, the environment, a file or the run
//! folder, and a role started without it stops.
//!
//! **Covered**: another process, of the same user or not, that can read and write the run's
//! shared-memory files (open them, rewrite messages in place, open the run's services as a
//! node and publish on them, send copies of messages it read) but can read neither our
//! processes' memory nor the key's pipe. It cannot make a message any reader accepts: not a
//! chunk, a batch or a request, not a weights version (the probe that locked both actors onto
//! a rewritten version is `unauthenticated`), not a heartbeat, an episode report or a status.
//! It can send copies of real messages again; none can hold a stream up or move anything past
//! its real sender, since only accepted messages move a reader and no copy is ahead of its
//! sender: a chunk's place is its sender's epoch ([`wire::new_epoch`]) and sequence, and a copy
//! goes back (`out_of_order`); a batch answer must answer the client's outstanding request (its
//! id and epoch), and one rejected leaves the request outstanding; weights are taken only newer
//! than those held; telemetry must come from the sender's current process (its pid) and not go
//! back. What copies can still do: a replay restarted after the copy was made may store one old
//! chunk before its stream's real ones, a freshly started actor may load an older real weights
//! version before the newest, the learner's smoothed episode returns (not the launcher's records)
//! may count an old report again, and a copied request makes the replay sample a batch its
//! learner ignores.
//!
//! **Not covered**: a process that can read our processes' memory or descriptors (ptrace,
//! `/proc/<pid>/mem`, `/proc/<pid>/fd`: another process of the same user may, unless the
//! system restricts ptrace, e.g. Yama's `ptrace_scope` 1 or more for non-descendants), which
//! can take the key; root; and availability: a writer can still truncate or delete the run's
//! segments, corrupt iceoryx2's allocator state inside them or fill the queues, which crashes,
//! stalls or slows processes (the launcher restarts them, see the reliability guide), without
//! making a forged value accepted. Messages are authenticated, not encrypted: anyone who can
//! read the segments reads the data.

mod batches;
pub mod bounds;
mod error;
mod key;
mod shared;
mod telemetry;
mod trajectory;
mod transport;
mod weights;
pub mod wire;

pub use batches::{BatchServer, ReplayClient, RENEW_PUBLISHER_AFTER, RESEND_AFTER};
pub use bounds::RunBounds;
pub use ctxrace_config::replay::DEFAULT_MAX_BATCH_FLOATS;
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
/// (the `ctxrace-ipc-inject` crate's `Held`) at exactly that point and show that it makes no
/// difference.
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

/// A test's (or a probe's) own run prefix, its shared memory removed when dropped, even when
/// the test panics (best effort: nodes still alive keep it).
pub struct Isolated(pub String);

impl Isolated {
    /// The prefix `test-<name>-<pid>`.
    pub fn new(name: &str) -> Self {
        Self(run_prefix(&format!("test-{name}-{}", std::process::id())))
    }
}

impl Drop for Isolated {
    fn drop(&mut self) {
        let _ = cleanup(&self.0);
    }
}
