//! One run's iceoryx2 setup: the per-run prefix, the raised service limits, the process's node,
//! the settings of every service, and the end-of-run cleanup.

use super::wire::{
    BatchHeader, BatchRequest, ChunkHeader, EpisodeMetrics, Heartbeat, ReplayStatus, WeightsHeader,
};
use anyhow::{anyhow, Context as _, Result};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;
use std::path::Path as StdPath;
use std::time::{Duration, Instant};

/// Chunks each actor may have queued at the replay before its sends wait.
pub const TRAJECTORY_BUFFER: usize = 64;
/// Nodes besides the actors that may open a service (replay, learner, launcher, tools).
const EXTRA_NODES: usize = 8;

/// Maps any iceoryx2 error (they are plain enums) to an error naming what failed.
pub(crate) fn ice<E: Debug>(what: &'static str) -> impl FnOnce(E) -> anyhow::Error {
    move |e| anyhow!("iceoryx2: {what}: {e:?}")
}

/// A flag that turns true on SIGTERM or SIGINT, for a process's loop to stop cleanly. (The
/// nodes' own signal handling is off: iceoryx2 resets its flag when read, so a blocking send
/// could swallow the request.)
pub fn termination_flag() -> Result<std::sync::Arc<std::sync::atomic::AtomicBool>> {
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, flag.clone())
            .map_err(|e| anyhow!("installing the handler of signal {signal}: {e}"))?;
    }
    Ok(flag)
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

/// The iceoryx2 configuration of a run: its own prefix, so that two runs on one machine never
/// see each other, and defaults raised for `actors` actors.
pub fn iceoryx_config(prefix: &str, actors: usize) -> Result<Config> {
    let mut config = Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes())
        .map_err(|e| anyhow!("invalid iceoryx2 prefix {prefix:?}: {e:?}"))?;
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

/// A process's handle on a run's transport: the configuration and one iceoryx2 node. Every
/// endpoint of [`super`] is created from it.
pub struct RunTransport {
    node: Node<ipc::Service>,
    prefix: String,
    actors: usize,
}

impl RunTransport {
    /// Joins the run with prefix `prefix` (see [`run_prefix`]) of `actors` actors as a node named
    /// `role`. Signal handling is left to the process (see [`termination_flag`]).
    pub fn open(prefix: &str, actors: usize, role: &str) -> Result<Self> {
        if actors == 0 {
            return Err(anyhow!("a run needs at least one actor"));
        }
        let config = iceoryx_config(prefix, actors)?;
        let name = NodeName::new(role).map_err(ice("node name"))?;
        let node = NodeBuilder::new()
            .config(&config)
            .name(&name)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(ice("create node"))?;
        Ok(Self {
            node,
            prefix: prefix.to_string(),
            actors,
        })
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

    /// Removes the resources of the run's dead nodes; returns how many were and were not removed.
    pub fn cleanup_dead_nodes(&self) -> (u64, u64) {
        let state = self.node.try_cleanup_dead_nodes();
        (state.cleanups, state.failed_cleanups)
    }

    fn max_nodes(&self) -> usize {
        self.actors + EXTRA_NODES
    }

    /// Actors -> replay: `[f32]` chunks; no overflow, so a full replay pushes back on actors.
    pub(crate) fn trajectory_service(
        &self,
    ) -> Result<PubSubFactory<ipc::Service, [f32], ChunkHeader>> {
        self.node
            .service_builder(&service_name("trajectory")?)
            .publish_subscribe::<[f32]>()
            .user_header::<ChunkHeader>()
            .max_publishers(self.actors * 2 + 2)
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
    pub(crate) fn weights_service(
        &self,
    ) -> Result<PubSubFactory<ipc::Service, [u8], WeightsHeader>> {
        self.node
            .service_builder(&service_name("weights")?)
            .publish_subscribe::<[u8]>()
            .user_header::<WeightsHeader>()
            .max_publishers(2)
            .max_subscribers(self.max_nodes())
            .max_nodes(self.max_nodes())
            .subscriber_max_buffer_size(1)
            .subscriber_max_borrowed_samples(1)
            .history_size(1)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(ice("weights service"))
    }

    /// Learner -> replay: batch requests.
    pub(crate) fn request_service(&self) -> Result<PubSubFactory<ipc::Service, BatchRequest, ()>> {
        self.small_service("batch_request", 16, 0)
    }

    /// Replay -> learner: batches.
    pub(crate) fn batch_service(&self) -> Result<PubSubFactory<ipc::Service, [f32], BatchHeader>> {
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
    pub(crate) fn metrics_service(
        &self,
    ) -> Result<PubSubFactory<ipc::Service, EpisodeMetrics, ()>> {
        self.small_service("metrics", 1024, 0)
    }

    /// Actors -> launcher: heartbeats.
    pub(crate) fn heartbeat_service(&self) -> Result<PubSubFactory<ipc::Service, Heartbeat, ()>> {
        self.small_service("heartbeat", 256, 0)
    }

    /// Replay -> launcher: counters, history 1.
    pub(crate) fn status_service(&self) -> Result<PubSubFactory<ipc::Service, ReplayStatus, ()>> {
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
    pub fn listener(&self, wake: Wake) -> Result<Listener<ipc::Service>> {
        self.event_service(wake)?
            .listener_builder()
            .create()
            .map_err(ice("listener"))
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
/// ports exist) between checks. The listener must exist before the first check, so that a
/// notification sent in between is not lost.
pub(crate) fn wait_until(
    ready: &Listener<ipc::Service>,
    timeout: Duration,
    mut connected: impl FnMut() -> bool,
) -> Result<bool> {
    let start = Instant::now();
    loop {
        if connected() {
            return Ok(true);
        }
        let left = timeout.saturating_sub(start.elapsed());
        if left.is_zero() {
            return Ok(false);
        }
        // Wake at least every 100 ms: a peer that started before our listener notified nobody.
        ready
            .timed_wait(|_| {}, left.min(Duration::from_millis(100)))
            .map_err(ice("wait for peer"))?;
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
}

/// Ends a run's transport: removes the resources of its dead nodes and, if none of its nodes is
/// alive any more, every shared-memory and management file carrying its prefix.
pub fn cleanup(prefix: &str) -> Result<CleanupReport> {
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
    if alive == 0 {
        let root = std::str::from_utf8(config.global.root_path().as_bytes())
            .context("iceoryx2 root path is not UTF-8")?
            .to_string();
        for dir in [root.as_str(), "/dev/shm"] {
            report.files_removed += remove_prefixed(StdPath::new(dir), prefix)?;
        }
    }
    Ok(report)
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
                Err(e) => return Err(e).with_context(|| format!("removing {}", path.display())),
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
}
