//! The transport's one error type: what failed, where, and (where the user can) how to fix it.
//! Causes are chained as sources, not printed in the messages: a `{:#}` chain (the binary's)
//! names each once.

use iceoryx2::prelude::SemanticStringError;
use std::path::PathBuf;
use std::time::Duration;

/// Environment variable naming the folder of ctxrace's iceoryx2 management files.
pub const SHM_ROOT_ENV: &str = "CTXRACE_SHM_ROOT";

/// Why a run's transport could not be set up, or a message could not be sent or received.
#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    /// An iceoryx2 call failed: what was being done, and iceoryx2's error. (Each iceoryx2 call
    /// has its own error enum, some two dozen in all; the source keeps the one that failed.)
    #[error("iceoryx2: {what}")]
    Iceoryx {
        /// What was being done (`"create node"`, `"send chunk"`, ...).
        what: &'static str,
        /// iceoryx2's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A handler of SIGTERM or SIGINT could not be installed.
    #[error("installing the handler of signal {signal}")]
    Signal {
        /// The signal.
        signal: i32,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// This process's user id could not be read.
    #[error("reading this process's user id from /proc/self")]
    UserId(#[source] std::io::Error),
    /// The shared-memory folder could not be created.
    #[error(
        "creating the shared-memory folder {}; set {SHM_ROOT_ENV} to a folder of yours",
        .path.display()
    )]
    CreateRoot {
        /// The folder.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The shared-memory folder is another user's, open to others, or not a folder.
    #[error(
        "the shared-memory folder {} is not a private folder of user {uid} (owner {owner}, mode \
         {mode:o}{}): another user could read or block this run; remove it, or set \
         {SHM_ROOT_ENV} to a folder only you can enter",
        .path.display(),
        if *.is_dir { "" } else { ", not a folder" }
    )]
    RootNotPrivate {
        /// The folder.
        path: PathBuf,
        /// This process's user.
        uid: u32,
        /// The folder's owner.
        owner: u32,
        /// Its permission bits.
        mode: u32,
        /// Whether it is a folder.
        is_dir: bool,
    },
    /// A file of the run in shared memory belongs to another user.
    #[error(
        "{} belongs to user {owner}, not to this user ({uid}): another user could read or \
         corrupt this run's shared memory; remove it and start again",
        .path.display()
    )]
    ForeignFile {
        /// The file.
        path: PathBuf,
        /// Its owner.
        owner: u32,
        /// This process's user.
        uid: u32,
    },
    /// A segment of the run is empty (truncated under it): iceoryx2 0.10 would wait on it
    /// forever (its open retries a zero-size mapping without a timeout).
    #[error(
        "{} is empty: a segment of the run was truncated under it, and the run cannot go on; \
         stop it (the next `ctxrace train` removes its files) and continue with --resume",
        .path.display()
    )]
    TruncatedSegment {
        /// The segment.
        path: PathBuf,
    },
    /// A file or folder of the transport could not be read, listed, written or removed.
    #[error("{action} {}", .path.display())]
    File {
        /// What was being done (`"listing"`, `"writing"`, ...).
        action: &'static str,
        /// The file or folder.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A shared-memory file of the run could not be closed to group and others.
    #[error("restricting {} to its owner", .path.display())]
    Restrict {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The run's prefix is no iceoryx2 file name.
    #[error("invalid iceoryx2 prefix {prefix:?}")]
    Prefix {
        /// The prefix.
        prefix: String,
        /// iceoryx2's reason.
        #[source]
        source: SemanticStringError,
    },
    /// The shared-memory folder's path is no iceoryx2 path.
    #[error("shared-memory folder {root:?} is not a valid iceoryx2 path")]
    RootPath {
        /// The folder, as given to iceoryx2.
        root: String,
        /// iceoryx2's reason.
        #[source]
        source: SemanticStringError,
    },
    /// A run was opened with no actor.
    #[error("a run needs at least one actor")]
    NoActors,
    /// The replay's subscribers did not appear in time.
    #[error("the replay did not come up within {timeout:?} (prefix {prefix})")]
    ReplayDown {
        /// How long was waited.
        timeout: Duration,
        /// The run's prefix.
        prefix: String,
    },
    /// SIGTERM or SIGINT came while waiting for a peer: the process stops before it is up.
    #[error("stopped by a termination request while waiting for the replay (prefix {prefix})")]
    Terminated {
        /// The run's prefix.
        prefix: String,
    },
    /// An actor id outside the run.
    #[error("actor id {id} is not below the run's {actors} actors")]
    ActorId {
        /// The id.
        id: u32,
        /// Actors in the run.
        actors: usize,
    },
    /// A trajectory sender of sizes the wire format does not carry.
    #[error("obs_dim {obs_dim} must be 1 to {max_obs} and act_dim {act_dim} 1 to {max_act}")]
    StepDims {
        /// Observation size.
        obs_dim: usize,
        /// Action size.
        act_dim: usize,
        /// The largest observation the wire format carries.
        max_obs: usize,
        /// The largest action the wire format carries.
        max_act: usize,
    },
    /// A step of other sizes than its sender's.
    #[error(
        "step has obs {obs} and action {action}, the sender was made for {want_obs} and \
         {want_action}"
    )]
    StepSize {
        /// The step's observation size.
        obs: usize,
        /// The step's action size.
        action: usize,
        /// The sender's observation size.
        want_obs: usize,
        /// The sender's action size.
        want_action: usize,
    },
    /// Weights larger than the publisher preallocated.
    #[error("weights of {len} bytes exceed the preallocated {max} bytes")]
    WeightsTooLarge {
        /// Their size.
        len: usize,
        /// The largest the publisher takes.
        max: usize,
    },
    /// A batch larger than the server preallocated.
    #[error("batch of {len} floats exceeds the preallocated {max}")]
    BatchTooLarge {
        /// Its floats.
        len: usize,
        /// The most the server takes.
        max: usize,
    },
    /// A batch size does not fit the wire format's 32-bit fields.
    #[error("a batch size does not fit the wire format's 32-bit fields")]
    WireSize(#[from] std::num::TryFromIntError),
    /// The run's key could not be drawn, handed to a child or read from the launcher.
    #[error("{0}")]
    Key(String),
}

impl IpcError {
    /// Whether a restarted process would meet this again: the run's shared memory is unusable
    /// (a segment truncated under it, a file or folder another user owns or can enter), so
    /// that the process exits as on a bad configuration and the launcher stops the run at once
    /// instead of spending its restarts.
    pub fn is_permanent(&self) -> bool {
        matches!(
            self,
            Self::TruncatedSegment { .. } | Self::ForeignFile { .. } | Self::RootNotPrivate { .. }
        )
    }
}

/// The outcome of a transport operation.
pub type Result<T, E = IpcError> = std::result::Result<T, E>;

/// Maps an iceoryx2 error (each call has its own enum) to an [`IpcError::Iceoryx`] naming what
/// failed.
pub(crate) fn ice<E: std::error::Error + Send + Sync + 'static>(
    what: &'static str,
) -> impl FnOnce(E) -> IpcError {
    move |e| IpcError::Iceoryx {
        what,
        source: Box::new(e),
    }
}
