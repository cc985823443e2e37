//! One run's iceoryx2 setup: the per-run prefix, the user's private root folder, the raised
//! service limits, the process's node, the settings of every service, the end-of-run cleanup,
//! and the sweep of runs whose launcher died.

use super::wire::{
    BatchHeader, BatchRequest, ChunkHeader, EpisodeReport, Heartbeat, ReplayStatus, WeightsHeader,
};
use crate::error::SHM_ROOT_ENV;
use crate::error::{ice, IpcError, Result};
use crate::key::RunKey;
use iceoryx2::port::listener::{Listener, ListenerWaitError};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;
use std::os::unix::fs::{DirBuilderExt as _, MetadataExt as _, PermissionsExt as _};
use std::path::{Path as StdPath, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

/// Chunks each actor may have queued at the replay before its sends wait: 16 chunks of at most
/// 64 steps, so that an actor the replay's rate limiter holds up has at most about a thousand
/// steps of older policies in flight (64 before: four times as many, for no throughput: `bench
/// ipc` and the soak store as many steps a second with 16).
pub const TRAJECTORY_BUFFER: usize = 16;
/// Nodes besides the actors that may open a service (replay, learner, launcher, tools).
const EXTRA_NODES: usize = 8;

/// The process's flag that turns true on SIGTERM or SIGINT, for its loop to stop cleanly. (The
/// nodes' own signal handling is off: iceoryx2 resets its flag when read, so a blocking send
/// could swallow the request.) Made once, at the first call: a process that calls it first thing
/// keeps a termination that arrives while it starts up (restoring a snapshot, loading a
/// checkpoint) for its loop, instead of dying of it without its last report. It is also what this
/// crate's waits consult when a signal interrupts them ([`termination_requested`]).
pub fn termination_flag() -> Result<Arc<AtomicBool>> {
    if let Some(flag) = PROCESS_TERMINATION.get() {
        return Ok(flag.clone());
    }
    let flag = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, flag.clone())
            .map_err(|source| IpcError::Signal { signal, source })?;
    }
    let _ = PROCESS_TERMINATION.set(flag.clone());
    Ok(flag)
}

/// The process's [`termination_flag`].
static PROCESS_TERMINATION: OnceLock<Arc<AtomicBool>> = OnceLock::new();

/// Whether SIGTERM or SIGINT reached this process since its first [`termination_flag`] (false
/// when it made none: a termination signal then ends it by default).
pub(crate) fn termination_requested() -> bool {
    PROCESS_TERMINATION
        .get()
        .is_some_and(|flag| flag.load(Ordering::Relaxed))
}

/// `listener.timed_wait` up to `timeout`, returning the events seen. A wait interrupted by a
/// signal (EINTR: SIGCONT after SIGSTOP, SIGTERM, any handled signal) is no error: it counts as
/// a wait that saw nothing, and the caller's loop goes on to its own deadline, or stops early
/// where it consults [`termination_requested`] (a learner waiting for a batch must still write
/// its last checkpoint, an actor closing must still deliver or count its chunks). `what` names
/// the wait in the error.
pub(crate) fn timed_wait(
    listener: &Listener<ipc::Service>,
    timeout: Duration,
    what: &'static str,
) -> Result<u64> {
    match listener.timed_wait(|_| {}, timeout) {
        Err(ListenerWaitError::InterruptSignal) => Ok(0),
        result => result.map_err(ice(what)),
    }
}

/// The prefix of a run: `ctxrace_<run id>_`, with characters other than ASCII letters, digits,
/// `-` and `.` in the id replaced by `-`.
pub fn run_prefix(run_id: &str) -> String {
    let id: String = run_id
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '-'
            }
        })
        .collect();
    format!("ctxrace_{id}_")
}

/// The folder of this user's iceoryx2 management files (`nodes/`, `services/`, the runs' owner
/// files): `$CTXRACE_SHM_ROOT`, else `$XDG_RUNTIME_DIR/ctxrace`, else `/tmp/ctxrace-<uid>`.
/// It is created with mode 0700 and refused when another user owns it or others may enter it: iceoryx2's default root, `/tmp/iceoryx2`, is shared by every
/// user, and whoever creates it first decides who may use it. (The shared memory itself lives in
/// `/dev/shm`, readable and writable by its owner only: see [`RunTransport::open`].)
pub fn shm_root() -> Result<PathBuf> {
    let uid = user_id()?;
    let root = match std::env::var_os(SHM_ROOT_ENV) {
        Some(dir) => PathBuf::from(dir),
        None => match std::env::var_os("XDG_RUNTIME_DIR") {
            Some(dir) if StdPath::new(&dir).is_dir() => PathBuf::from(dir).join("ctxrace"),
            _ => PathBuf::from(format!("/tmp/ctxrace-{uid}")),
        },
    };
    match std::fs::DirBuilder::new().mode(0o700).create(&root) {
        Err(source) if source.kind() != std::io::ErrorKind::AlreadyExists => {
            return Err(IpcError::CreateRoot { path: root, source })
        }
        _ => {}
    }
    let meta = std::fs::symlink_metadata(&root).map_err(|source| IpcError::File {
        action: "reading the shared-memory folder",
        path: root.clone(),
        source,
    })?;
    if !meta.is_dir() || meta.uid() != uid || meta.permissions().mode() & 0o077 != 0 {
        return Err(IpcError::RootNotPrivate {
            path: root,
            uid,
            owner: meta.uid(),
            mode: meta.permissions().mode() & 0o7777,
            is_dir: meta.is_dir(),
        });
    }
    Ok(root)
}

/// The iceoryx2 configuration of a run: its own prefix, so that two runs on one machine never
/// see each other, the user's private root folder ([`shm_root`]), and defaults raised for
/// `actors` actors.
pub fn iceoryx_config(prefix: &str, actors: usize) -> Result<Config> {
    let mut config = Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes()).map_err(|source| IpcError::Prefix {
        prefix: prefix.to_string(),
        source,
    })?;
    let root = format!("{}/", shm_root()?.display());
    let root = Path::new(root.as_bytes()).map_err(|source| IpcError::RootPath {
        root: root.clone(),
        source,
    })?;
    config.global.set_root_path(&root);
    config.global.node.cleanup_dead_nodes_on_creation = true;
    let ps = &mut config.defaults.publish_subscribe;
    ps.max_publishers = actors + EXTRA_NODES;
    ps.max_subscribers = actors + EXTRA_NODES;
    ps.max_nodes = actors + EXTRA_NODES;
    let ev = &mut config.defaults.event;
    ev.max_notifiers = actors + EXTRA_NODES;
    ev.max_listeners = actors + EXTRA_NODES;
    ev.max_nodes = actors + EXTRA_NODES;
    Ok(config)
}

/// A process's handle on a run's transport: the configuration, one iceoryx2 node and the run's
/// key. Every endpoint of [`super`] is created from it, and seals what it sends and checks what
/// it receives with the key. Its services (`*_service`) are public so that a probe of a run (the
/// tests' `ctxrace-ipc-inject`) can open raw ports on them, as any process of the user can by
/// their names; the run's processes only ever use the endpoints.
pub struct RunTransport {
    node: Node<ipc::Service>,
    prefix: String,
    actors: usize,
    key: RunKey,
}

impl RunTransport {
    /// Joins the run with prefix `prefix` (see [`run_prefix`]) of `actors` actors and key `key`
    /// as a node named `role`. Signal handling is left to the process (see [`termination_flag`]). iceoryx2 0.10
    /// creates the run's `...node.<version>.global_mgmt` segment in `/dev/shm` readable and
    /// writable by everyone (mode 0666: `enable_global_access` in its
    /// `GlobalManagementSegment`, not configurable): every node closes it to its owner once
    /// created, and so do [`remove_dead_nodes`] and [`cleanup`] (a node that died or hung
    /// before closing it, after recreating it, leaves it open only until then).
    pub fn open(prefix: &str, actors: usize, role: &str, key: &RunKey) -> Result<Self> {
        if actors == 0 {
            return Err(IpcError::NoActors);
        }
        let config = iceoryx_config(prefix, actors)?;
        let name = NodeName::new(role).map_err(ice("node name"))?;
        check_segments(StdPath::new(SHM_DIR), prefix, TRUNCATION_GRACE)?;
        let node = NodeBuilder::new()
            .config(&config)
            .name(&name)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(ice("create node"))?;
        restrict_to_owner(StdPath::new(SHM_DIR), prefix)?;
        Ok(Self {
            node,
            prefix: prefix.to_string(),
            actors,
            key: key.clone(),
        })
    }

    /// The run's key.
    pub fn key(&self) -> &RunKey {
        &self.key
    }

    /// The run's prefix.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// Actors in the run; actor ids are below it.
    pub fn actors(&self) -> usize {
        self.actors
    }

    /// The process's node.
    pub fn node(&self) -> &Node<ipc::Service> {
        &self.node
    }

    fn max_nodes(&self) -> usize {
        self.actors + EXTRA_NODES
    }

    /// Actor `actor_id` -> replay: `[f32]` chunks; no overflow, so a full replay pushes back on
    /// the actor. One service per actor, so that the replay can take from each in turn (a
    /// subscriber scans its publishers from the first, which would favour one actor).
    pub fn trajectory_service(
        &self,
        actor_id: usize,
    ) -> Result<PubSubFactory<ipc::Service, [f32], ChunkHeader>> {
        self.node
            .service_builder(&service_name(&format!("trajectory/{actor_id}"))?)
            .publish_subscribe::<[f32]>()
            .user_header::<ChunkHeader>()
            .max_publishers(4)
            .max_subscribers(2)
            .max_nodes(self.max_nodes())
            .subscriber_max_buffer_size(TRAJECTORY_BUFFER)
            .subscriber_max_borrowed_samples(2)
            .history_size(0)
            .enable_safe_overflow(false)
            .open_or_create()
            .map_err(ice("trajectory service"))
    }

    /// Learner -> actors: weights bytes, history 1 so late subscribers get the newest.
    pub fn weights_service(&self) -> Result<PubSubFactory<ipc::Service, [u8], WeightsHeader>> {
        self.node
            .service_builder(&service_name("weights")?)
            .publish_subscribe::<[u8]>()
            .user_header::<WeightsHeader>()
            .max_publishers(2)
            .max_subscribers(self.max_nodes())
            .max_nodes(self.max_nodes())
            .subscriber_max_buffer_size(1)
            // `WeightsReceiver::latest_with` copies each blob out and releases it at once; two
            // leave room for a broadcast arriving while another is still held (with one, such a
            // receive failed with ExceedsMaxBorrows and the actor stopped)
            .subscriber_max_borrowed_samples(2)
            .history_size(1)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(ice("weights service"))
    }

    /// Learner -> replay: batch requests.
    pub fn request_service(&self) -> Result<PubSubFactory<ipc::Service, BatchRequest, ()>> {
        self.small_service("batch_request", 16, 0)
    }

    /// Replay -> learner: batches.
    pub fn batch_service(&self) -> Result<PubSubFactory<ipc::Service, [f32], BatchHeader>> {
        self.node
            .service_builder(&service_name("batch")?)
            .publish_subscribe::<[f32]>()
            .user_header::<BatchHeader>()
            .max_publishers(2)
            .max_subscribers(2)
            .max_nodes(self.max_nodes())
            .subscriber_max_buffer_size(4)
            .subscriber_max_borrowed_samples(1)
            .history_size(0)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(ice("batch service"))
    }

    /// Actors -> launcher: episode metrics.
    pub fn metrics_service(&self) -> Result<PubSubFactory<ipc::Service, EpisodeReport, ()>> {
        self.small_service("metrics", 1024, 0)
    }

    /// Actors -> launcher: heartbeats.
    pub fn heartbeat_service(&self) -> Result<PubSubFactory<ipc::Service, Heartbeat, ()>> {
        self.small_service("heartbeat", 256, 0)
    }

    /// Replay -> launcher: counters, history 1.
    pub fn status_service(&self) -> Result<PubSubFactory<ipc::Service, ReplayStatus, ()>> {
        self.small_service("replay_status", 1, 1)
    }

    fn small_service<T: Debug + ZeroCopySend>(
        &self,
        name: &'static str,
        buffer: usize,
        history: usize,
    ) -> Result<PubSubFactory<ipc::Service, T, ()>> {
        self.node
            .service_builder(&service_name(name)?)
            .publish_subscribe::<T>()
            .max_publishers(self.max_nodes() + self.actors)
            .max_subscribers(self.max_nodes())
            .max_nodes(self.max_nodes())
            .subscriber_max_buffer_size(buffer)
            .history_size(history)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(ice(name))
    }

    /// An event service; `wake` names whom it wakes.
    fn event_service(&self, wake: Wake) -> Result<EventFactory<ipc::Service>> {
        self.node
            .service_builder(&service_name(wake.name())?)
            .event()
            .max_notifiers(self.max_nodes() + self.actors)
            .max_listeners(self.max_nodes())
            .max_nodes(self.max_nodes())
            .open_or_create()
            .map_err(ice(wake.name()))
    }

    /// A notifier on one of the run's event services.
    pub fn notifier(&self, wake: Wake) -> Result<Notifier<ipc::Service>> {
        self.event_service(wake)?
            .notifier_builder()
            .create()
            .map_err(ice("notifier"))
    }

    /// A listener on one of the run's event services, to attach to a `WaitSet`.
    pub(crate) fn listener(&self, wake: Wake) -> Result<Listener<ipc::Service>> {
        self.event_service(wake)?
            .listener_builder()
            .create()
            .map_err(ice("listener"))
    }
}

/// What a serving loop's turn asks for next (see [`RunTransport::serve`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Next {
    /// Another turn at once: the last one was busy.
    Poll,
    /// Sleep until woken or a tick has passed.
    Sleep,
    /// Leave the loop.
    Stop,
}

impl RunTransport {
    /// Runs `turn` until it returns [`Next::Stop`] or, with `handle_signals`, SIGTERM or SIGINT
    /// arrives; between turns it sleeps in an iceoryx2 `WaitSet` on the event `wake`, at most
    /// `tick`. Returns whether a termination signal ended the loop; an error of `turn` ends it
    /// too and is returned as it is (the transport's own errors as `E`).
    pub fn serve<E: From<IpcError>>(
        &self,
        wake: Wake,
        tick: Duration,
        handle_signals: bool,
        mut turn: impl FnMut() -> Result<Next, E>,
    ) -> Result<bool, E> {
        let listener = self.listener(wake)?;
        let signals = if handle_signals {
            SignalHandlingMode::HandleTerminationRequests
        } else {
            SignalHandlingMode::Disabled
        };
        let waitset = WaitSetBuilder::new()
            .signal_handling_mode(signals)
            .create::<ipc::Service>()
            .map_err(ice("waitset"))?;
        let _wake_guard = waitset
            .attach_notification(&listener)
            .map_err(ice("attach wake"))?;
        let _tick_guard = waitset.attach_interval(tick).map_err(ice("attach tick"))?;
        loop {
            let timeout = match turn()? {
                // a termination that came before the waitset's own handling (while starting up)
                _ if handle_signals && termination_requested() => return Ok(true),
                Next::Stop => return Ok(false),
                Next::Poll => Duration::ZERO,
                Next::Sleep => tick,
            };
            let result = waitset
                .wait_and_process_once_with_timeout(|_| CallbackProgression::Continue, timeout)
                .map_err(ice("wait"))?;
            // An interrupted wait (SIGCONT after SIGSTOP, or EINTR) is no termination: with
            // `handle_signals`, a SIGTERM or SIGINT that interrupted it is reported by the next
            // wait as a termination request.
            if result == iceoryx2::waitset::WaitSetRunResult::TerminationRequest {
                return Ok(true);
            }
            listener.try_wait(|_| {}).map_err(ice("drain wake"))?;
        }
    }
}

/// The run's event services, each named after whom it wakes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wake {
    /// The replay loop: a chunk or a request arrived.
    Replay,
    /// The learner: a batch arrived.
    Learner,
    /// Actors: new weights.
    Actors,
    /// Anyone waiting for the replay to come up: its subscribers exist.
    ReplayReady,
}

impl Wake {
    fn name(self) -> &'static str {
        match self {
            Wake::Replay => "wake_replay",
            Wake::Learner => "wake_learner",
            Wake::Actors => "wake_actors",
            Wake::ReplayReady => "replay_ready",
        }
    }
}

fn service_name(name: &str) -> Result<ServiceName> {
    ServiceName::new(&format!("ctxrace/{name}")).map_err(ice("service name"))
}

/// Waits until `connected()` holds, sleeping on `ready` (notified by the other side once its
/// ports exist) between checks; [`IpcError::ReplayDown`] after `timeout`, and
/// [`IpcError::Terminated`] once a termination is requested, in the run of `prefix`. The
/// listener must exist before the first check, so that a notification sent in between is not
/// lost.
pub(crate) fn wait_until(
    ready: &Listener<ipc::Service>,
    timeout: Duration,
    prefix: &str,
    mut connected: impl FnMut() -> bool,
) -> Result<()> {
    let start = Instant::now();
    loop {
        if connected() {
            return Ok(());
        }
        if termination_requested() {
            return Err(IpcError::Terminated {
                prefix: prefix.to_string(),
            });
        }
        let left = timeout.saturating_sub(start.elapsed());
        if left.is_zero() {
            return Err(IpcError::ReplayDown {
                timeout,
                prefix: prefix.to_string(),
            });
        }
        // Wake at least every 100 ms: a peer that started before our listener notified nobody.
        timed_wait(ready, left.min(Duration::from_millis(100)), "wait for peer")?;
    }
}

/// What [`cleanup`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CleanupReport {
    /// Dead nodes whose resources were removed.
    pub dead_nodes_removed: u64,
    /// Dead nodes that could not be removed.
    pub dead_nodes_failed: u64,
    /// Nodes of the run still alive (files are only removed when there are none).
    pub alive_nodes: u64,
    /// Files and directories of the run removed.
    pub files_removed: u64,
    /// Shared-memory files of the run that others could read or write (iceoryx2 0.10 makes its
    /// `global_mgmt` segment mode 0666 whenever it creates it), closed to their owner.
    pub files_restricted: u64,
}

/// Where POSIX shared memory lives.
const SHM_DIR: &str = "/dev/shm";

/// How long an empty segment may stay empty before it counts as truncated: iceoryx2 sizes a
/// segment right after creating it, so a segment another process is creating is empty only for
/// an instant.
const TRUNCATION_GRACE: Duration = Duration::from_secs(2);

/// Refuses to join a run one of whose segments in `dir` (its name starting with `prefix`) is
/// empty for longer than `grace`: iceoryx2 0.10 would wait on it forever, a process restarted
/// into a run whose `global_mgmt` had been truncated hung for the rest of the run. An empty
/// `global_mgmt` (a node counter for unique ids, which also carry the pid and creation time) is
/// removed instead, for the node to make a fresh one; any other empty segment is an error.
fn check_segments(dir: &StdPath, prefix: &str, grace: Duration) -> Result<()> {
    let empty = || -> Vec<PathBuf> {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return Vec::new();
        };
        entries
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().starts_with(prefix))
            .filter(|e| e.metadata().is_ok_and(|m| m.is_file() && m.len() == 0))
            .map(|e| e.path())
            .collect()
    };
    let start = Instant::now();
    let mut truncated = empty();
    while !truncated.is_empty() && start.elapsed() < grace {
        std::thread::sleep(Duration::from_millis(50));
        truncated.retain(|p| std::fs::metadata(p).is_ok_and(|m| m.len() == 0));
    }
    for path in truncated {
        if !path.to_string_lossy().ends_with("global_mgmt") {
            return Err(IpcError::TruncatedSegment { path });
        }
        tracing::warn!(
            "{} is empty (truncated): removed for a fresh one",
            path.display()
        );
        match std::fs::remove_file(&path) {
            Err(source) if source.kind() != std::io::ErrorKind::NotFound => {
                return Err(IpcError::File {
                    action: "removing",
                    path,
                    source,
                })
            }
            _ => {}
        }
    }
    Ok(())
}

/// This process's user id (the owner of `/proc/self`).
fn user_id() -> Result<u32> {
    std::fs::metadata("/proc/self")
        .map(|m| m.uid())
        .map_err(IpcError::UserId)
}

/// Takes group and others' permissions off every file in `dir` whose name starts with `prefix`
/// and that this user owns; refuses a file another user owns (it could read or corrupt the run).
/// Returns how many files it closed.
fn restrict_to_owner(dir: &StdPath, prefix: &str) -> Result<u64> {
    let mut restricted = 0;
    let uid = user_id()?;
    let entries = std::fs::read_dir(dir).map_err(|source| IpcError::File {
        action: "listing",
        path: dir.to_path_buf(),
        source,
    })?;
    for entry in entries.flatten() {
        if !entry.file_name().to_string_lossy().starts_with(prefix) {
            continue;
        }
        let path = entry.path();
        let Ok(meta) = std::fs::symlink_metadata(&path) else {
            continue; // removed meanwhile
        };
        if meta.uid() != uid {
            return Err(IpcError::ForeignFile {
                path,
                owner: meta.uid(),
                uid,
            });
        }
        let mode = meta.permissions().mode();
        if mode & 0o077 != 0 {
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode & 0o700))
                .map_err(|source| IpcError::Restrict { path, source })?;
            restricted += 1;
        }
    }
    Ok(restricted)
}

/// Removes the resources of the dead nodes of the run with `prefix` (a crashed process's
/// ports, so that its peers stop waiting for it); counts the live nodes. It opens no node, and
/// can be run on a thread of its own.
pub fn remove_dead_nodes(prefix: &str) -> Result<CleanupReport> {
    let config = iceoryx_config(prefix, 1)?;
    let mut report = CleanupReport::default();
    let mut alive = 0;
    Node::<ipc::Service>::list(&config, |state| {
        match state {
            NodeState::Alive(_) => alive += 1,
            NodeState::Dead(view) => match view.try_remove_stale_resources() {
                Ok(()) => report.dead_nodes_removed += 1,
                Err(_) => report.dead_nodes_failed += 1,
            },
            NodeState::Inaccessible(_) | NodeState::Undefined(_) => report.dead_nodes_failed += 1,
        }
        CallbackProgression::Continue
    })
    .map_err(ice("list nodes"))?;
    report.alive_nodes = alive;
    // a node created since the last check may have made `global_mgmt` again, world-writable
    report.files_restricted = restrict_to_owner(StdPath::new(SHM_DIR), prefix)?;
    Ok(report)
}

/// Ends a run's transport: removes the resources of its dead nodes and, if none of its nodes is
/// alive any more, every shared-memory and management file carrying its prefix.
pub fn cleanup(prefix: &str) -> Result<CleanupReport> {
    let mut report = remove_dead_nodes(prefix)?;
    if report.alive_nodes == 0 {
        for dir in [shm_root()?, PathBuf::from(SHM_DIR)] {
            report.files_removed += remove_prefixed(&dir, prefix)?;
        }
    }
    Ok(report)
}

/// Marks the run with `prefix` as owned by this process: a file in [`shm_root`] naming its pid
/// and start time, which [`sweep_orphaned_runs`] reads after the process died. [`cleanup`]
/// removes it with the run's other files.
pub fn claim_run(prefix: &str) -> Result<()> {
    let path = shm_root()?.join(format!("{prefix}{OWNER_SUFFIX}"));
    let pid = std::process::id();
    let text = format!("{pid} {}\n", process_start(pid).unwrap_or(0));
    ctxrace_run::run_dir::write_atomic(&path, text.as_bytes()).map_err(|source| IpcError::File {
        action: "writing",
        path,
        source,
    })
}

const OWNER_SUFFIX: &str = "owner";

/// A process's start time in clock ticks since boot (`/proc/<pid>/stat` field 22), which tells a
/// pid reused by another process from the one that wrote an owner file.
fn process_start(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // the command may hold spaces and parentheses: fields count from the last ')'
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().nth(19)?.parse().ok()
}

/// The processes other than this one started for the run with `prefix` (its replay, learner
/// and actors, which carry the prefix among their arguments), from `/proc/<pid>/cmdline`.
fn processes_of(prefix: &str) -> Vec<u32> {
    use std::io::Read as _;
    let me = std::process::id();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    let pids = entries
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok());
    pids.filter(|&pid| pid != me)
        .filter(|pid| {
            let mut cmdline = Vec::new();
            let read = std::fs::File::open(format!("/proc/{pid}/cmdline"))
                .and_then(|f| f.take(1 << 16).read_to_end(&mut cmdline));
            read.is_ok()
                && cmdline
                    .split(|&b| b == 0)
                    .any(|arg| arg == prefix.as_bytes())
        })
        .collect()
}

/// What [`sweep_orphaned_runs`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Sweep {
    /// The prefixes of the runs whose files were removed.
    pub swept: Vec<String>,
    /// The orphaned runs left alone because processes of theirs still live (prefix, pids).
    pub kept: Vec<(String, Vec<u32>)>,
}

/// Removes the shared memory of every ctxrace run whose owner ([`claim_run`]) is gone, as after
/// a killed launcher, and no process of which lives: its files are removed as files, without
/// opening them through iceoryx2, so that segments truncated or corrupted under a dead run can
/// neither stall the sweep (iceoryx2 waits on a segment it cannot read) nor crash it. Runs
/// whose owner lives are left alone, and so are orphaned runs whose processes still live.
pub fn sweep_orphaned_runs() -> Result<Sweep> {
    let root = shm_root()?;
    let mut sweep = Sweep::default();
    let entries = std::fs::read_dir(&root).map_err(|source| IpcError::File {
        action: "listing",
        path: root.clone(),
        source,
    })?;
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(prefix) = name.strip_suffix(OWNER_SUFFIX) else {
            continue;
        };
        if !prefix.starts_with("ctxrace_") {
            continue;
        }
        // a pid and a start time; anything else (a link, a FIFO, a large file) marks no owner
        let owner = ctxrace_run::run_dir::read_regular(&entry.path(), 64)
            .map(|bytes| String::from_utf8_lossy(&bytes).into_owned())
            .unwrap_or_default();
        let mut fields = owner.split_whitespace().map(|f| f.parse::<u64>().ok());
        let alive = match (fields.next().flatten(), fields.next().flatten()) {
            (Some(pid), Some(start)) => process_start(pid as u32).is_some_and(|s| s == start),
            _ => false,
        };
        if alive {
            continue;
        }
        let users = processes_of(prefix);
        if !users.is_empty() {
            sweep.kept.push((prefix.to_string(), users));
            continue;
        }
        for dir in [root.clone(), PathBuf::from(SHM_DIR)] {
            remove_prefixed(&dir, prefix)?;
        }
        sweep.swept.push(prefix.to_string());
    }
    Ok(sweep)
}

/// Removes every entry under `dir` (recursively) whose name starts with `prefix`.
fn remove_prefixed(dir: &StdPath, prefix: &str) -> Result<u64> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(0);
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let path = entry.path();
        let is_dir = entry.file_type().map(|t| t.is_dir()).unwrap_or(false);
        if entry.file_name().to_string_lossy().starts_with(prefix) {
            let result = if is_dir {
                std::fs::remove_dir_all(&path)
            } else {
                std::fs::remove_file(&path)
            };
            match result {
                Ok(()) => removed += 1,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(source) => {
                    return Err(IpcError::File {
                        action: "removing",
                        path,
                        source,
                    })
                }
            }
        } else if is_dir {
            removed += remove_prefixed(&path, prefix)?;
        }
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prefix_is_sanitised() {
        assert_eq!(run_prefix("exp 1/a"), "ctxrace_exp-1-a_");
        assert!(iceoryx_config(&run_prefix("x"), 16).is_ok());
    }

    #[test]
    fn the_root_folder_is_private() {
        let root = shm_root().unwrap();
        let mode = std::fs::metadata(&root).unwrap().permissions().mode();
        assert_eq!(mode & 0o077, 0, "{} has mode {mode:o}", root.display());
        let config = iceoryx_config(&run_prefix("x"), 1).unwrap();
        let configured = std::str::from_utf8(config.global.root_path().as_bytes()).unwrap();
        assert_eq!(configured, format!("{}/", root.display()));
    }

    /// iceoryx2 makes `global_mgmt` mode 0666 whenever it creates it: a node's open closes it,
    /// and if it is opened again (recreated by a node that died or hung before closing it), the
    /// supervisor's dead-node cleanup and the end-of-run cleanup close it again.
    #[test]
    fn global_mgmt_is_never_left_world_writable() {
        let isolated = crate::Isolated::new("global-mgmt");
        let prefix = isolated.0.clone();
        let t = RunTransport::open(&prefix, 1, "test", &crate::test_key()).unwrap();
        let mgmt = std::fs::read_dir(SHM_DIR)
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .find(|p| {
                let name = p.file_name().unwrap().to_string_lossy();
                name.starts_with(&prefix) && name.ends_with("global_mgmt")
            })
            .expect("the run's global_mgmt segment in /dev/shm");
        let mode = |p: &StdPath| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&mgmt), 0o600, "{} after open", mgmt.display());
        for clean in [remove_dead_nodes, cleanup] {
            std::fs::set_permissions(&mgmt, std::fs::Permissions::from_mode(0o666)).unwrap();
            let report = clean(&prefix).unwrap();
            assert_eq!(report.alive_nodes, 1);
            assert_eq!(report.files_restricted, 1, "{report:?}");
            assert_eq!(mode(&mgmt), 0o600, "{} after {report:?}", mgmt.display());
        }
        drop(t);
    }

    #[test]
    fn runs_whose_owner_died_are_swept_and_live_ones_kept() {
        let me = std::process::id();
        let root = shm_root().unwrap();
        // a run owned by a process that has exited, with files in both places
        let dead = run_prefix(&format!("test-orphan-{me}"));
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let gone = child.id();
        child.wait().unwrap();
        std::fs::write(
            root.join(format!("{dead}{OWNER_SUFFIX}")),
            format!("{gone} 1\n"),
        )
        .unwrap();
        let files = [
            root.join(format!("{dead}x.service")),
            PathBuf::from(format!("/dev/shm/{dead}data")),
        ];
        for f in &files {
            std::fs::write(f, b"left behind").unwrap();
        }
        // a segment truncated under the dead run: removed as a file, never opened
        let truncated = PathBuf::from(format!("/dev/shm/{dead}y.dynamic"));
        std::fs::write(&truncated, b"").unwrap();
        // a run this process owns
        let live = run_prefix(&format!("test-owned-{me}"));
        claim_run(&live).unwrap();
        let sweep = sweep_orphaned_runs().unwrap();
        assert!(sweep.swept.contains(&dead), "{sweep:?}");
        assert!(!sweep.swept.contains(&live), "{sweep:?}");
        for f in files.iter().chain([&truncated]) {
            assert!(!f.exists(), "{} is left", f.display());
        }
        assert!(root.join(format!("{live}{OWNER_SUFFIX}")).exists());
        cleanup(&live).unwrap();
        assert!(!root.join(format!("{live}{OWNER_SUFFIX}")).exists());
    }

    /// An empty `global_mgmt` is replaced and a node joins; any other empty segment of the run
    /// is refused by name (iceoryx2 would wait on either forever); a segment that fills within
    /// the grace is taken.
    #[test]
    fn truncated_segments_are_replaced_or_refused_never_waited_on() {
        let me = std::process::id();
        let prefix = run_prefix(&format!("test-truncated-{me}"));
        let mgmt = PathBuf::from(format!(
            "{SHM_DIR}/{prefix}9204dd183d1c4d8e1ff592a30766ffa6765aa8b5_node.0_10_0.global_mgmt"
        ));
        std::fs::write(&mgmt, b"").unwrap();
        let started = Instant::now();
        let node = RunTransport::open(&prefix, 1, "test", &crate::test_key()).unwrap();
        assert!(started.elapsed() < Duration::from_secs(10));
        assert!(std::fs::metadata(&mgmt).unwrap().len() > 0, "a fresh one");
        drop(node);
        let dynamic = PathBuf::from(format!("{SHM_DIR}/{prefix}x.dynamic"));
        std::fs::write(&dynamic, b"").unwrap();
        let err = check_segments(StdPath::new(SHM_DIR), &prefix, Duration::ZERO).unwrap_err();
        assert!(
            err.to_string().contains("x.dynamic is empty") && err.to_string().contains("--resume"),
            "{err}"
        );
        let filler = {
            let dynamic = dynamic.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(200));
                std::fs::write(dynamic, b"sized").unwrap();
            })
        };
        check_segments(StdPath::new(SHM_DIR), &prefix, Duration::from_secs(5)).unwrap();
        filler.join().unwrap();
        std::fs::remove_file(&dynamic).unwrap();
        cleanup(&prefix).unwrap();
    }

    /// An orphaned run (its owner gone) one of whose processes lives is left alone, with its pid.
    #[test]
    fn orphaned_runs_whose_processes_live_are_kept() {
        use std::os::unix::process::CommandExt as _;
        let me = std::process::id();
        let root = shm_root().unwrap();
        let prefix = run_prefix(&format!("test-orphan-busy-{me}"));
        let owner = root.join(format!("{prefix}{OWNER_SUFFIX}"));
        let mut gone = std::process::Command::new("true").spawn().unwrap();
        gone.wait().unwrap();
        std::fs::write(&owner, format!("{} 1\n", gone.id())).unwrap();
        // a process of the run: the prefix among its arguments, as the run's roles carry it
        let mut process = std::process::Command::new("sleep")
            .arg0(&prefix)
            .arg("30")
            .spawn()
            .unwrap();
        // its arguments readable (for an instant after exec, /proc shows none)
        let cmdline = format!("/proc/{}/cmdline", process.id());
        let started = Instant::now();
        while std::fs::read(&cmdline).is_ok_and(|c| c.is_empty()) {
            assert!(started.elapsed() < Duration::from_secs(5));
            std::thread::sleep(Duration::from_millis(5));
        }
        let sweep = sweep_orphaned_runs().unwrap();
        process.kill().unwrap();
        process.wait().unwrap();
        assert!(!sweep.swept.contains(&prefix), "{sweep:?}");
        assert!(
            sweep.kept.contains(&(prefix.clone(), vec![process.id()])),
            "{sweep:?}"
        );
        assert!(owner.exists());
        assert_eq!(sweep_orphaned_runs().unwrap().kept, vec![]);
        assert!(!owner.exists());
    }

    /// `(path, mode)` of everything under `dir` (recursively) whose name carries `prefix`, or
    /// that lies in a folder whose name does.
    fn modes_under(dir: &StdPath, prefix: &str, inside: bool) -> Vec<(PathBuf, u32)> {
        let mut found = Vec::new();
        for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let path = entry.path();
            let Ok(meta) = std::fs::symlink_metadata(&path) else {
                continue;
            };
            let ours = inside || entry.file_name().to_string_lossy().contains(prefix);
            if ours {
                found.push((path.clone(), meta.permissions().mode() & 0o7777));
            }
            if meta.is_dir() {
                found.extend(modes_under(&path, prefix, ours));
            }
        }
        found
    }

    #[test]
    fn every_file_of_a_run_is_closed_to_group_and_others() {
        let prefix = run_prefix(&format!("test-modes-{}", std::process::id()));
        let mut listing = Vec::new();
        {
            let t = RunTransport::open(&prefix, 2, "learner", &crate::test_key()).unwrap();
            let peer = RunTransport::open(&prefix, 2, "actor-0", &crate::test_key()).unwrap();
            // every service, with ports on both sides where data or connections get created
            let weights = t.weights_service().unwrap();
            let publisher = weights
                .publisher_builder()
                .initial_max_slice_len(64)
                .create()
                .unwrap();
            let peer_weights = peer.weights_service().unwrap();
            let subscriber = peer_weights.subscriber_builder().create().unwrap();
            let sample = publisher.loan_slice_uninit(8).unwrap();
            sample.write_from_slice(&[1u8; 8]).send().unwrap();
            assert!(subscriber.receive().unwrap().is_some());
            let chunks = t.trajectory_service(0).unwrap();
            let _chunk_sub = chunks.subscriber_builder().create().unwrap();
            let _chunk_pub = peer
                .trajectory_service(0)
                .unwrap()
                .publisher_builder()
                .initial_max_slice_len(8)
                .create()
                .unwrap();
            let _requests = t.request_service().unwrap().subscriber_builder().create();
            let _batches = t.batch_service().unwrap().subscriber_builder().create();
            let _metrics = t.metrics_service().unwrap();
            let _heartbeats = t.heartbeat_service().unwrap();
            let _status = t.status_service().unwrap();
            let _listeners: Vec<_> = [Wake::Replay, Wake::Learner, Wake::Actors, Wake::ReplayReady]
                .into_iter()
                .map(|w| (t.listener(w).unwrap(), peer.notifier(w).unwrap()))
                .collect();
            for dir in [PathBuf::from(SHM_DIR), shm_root().unwrap()] {
                listing.extend(modes_under(&dir, &prefix, false));
            }
        }
        cleanup(&prefix).unwrap();
        let text: Vec<String> = listing
            .iter()
            .map(|(p, m)| format!("{m:04o} {}", p.display()))
            .collect();
        eprintln!("{}", text.join("\n"));
        assert!(
            listing.iter().any(|(p, _)| p.starts_with(SHM_DIR)),
            "no shared memory listed: {text:?}"
        );
        let open: Vec<&String> = listing
            .iter()
            .zip(&text)
            .filter(|((_, mode), _)| mode & 0o077 != 0)
            .map(|(_, t)| t)
            .collect();
        assert!(open.is_empty(), "open to group or others: {open:#?}");
    }

    #[test]
    fn start_times_tell_a_live_owner() {
        let me = std::process::id();
        assert!(process_start(me).is_some_and(|t| t > 0));
        assert_eq!(process_start(u32::MAX), None);
    }
}
