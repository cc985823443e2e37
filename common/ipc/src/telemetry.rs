//! Actor and replay telemetry for the launcher: episode metrics, heartbeats, replay status, each
//! sealed with the run's key and naming its sender's process.

use super::bounds::{
    check_range, check_version, Counter, RunBounds, MAX_ACTOR_STEPS_PER_SEC, MAX_PROGRESS,
    MAX_STEP_REWARD,
};
use super::shared::read_once;
use super::transport::RunTransport;
use super::wire::{
    check_finite, check_sealed, EpisodeReport, Heartbeat, ReplayStatus, Sealed, WireError,
    FORMAT_VERSION, MAX_PENDING_REQUESTS, REASONS,
};
use super::RejectLog;
use crate::error::{ice, Result};
use crate::key::RunKey;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;
use std::time::Instant;

/// A publisher of plain `T` messages on `service`, one of the run's telemetry services (or its
/// batch requests); `what` names it in an error.
fn publisher<T: Debug + ZeroCopySend>(
    service: Result<PubSubFactory<ipc::Service, T, ()>>,
    what: &'static str,
) -> Result<Publisher<ipc::Service, T, ()>> {
    service?.publisher_builder().create().map_err(ice(what))
}

/// A subscriber to plain `T` messages on `service`; `what` names it in an error.
fn subscriber<T: Debug + ZeroCopySend>(
    service: Result<PubSubFactory<ipc::Service, T, ()>>,
    what: &'static str,
) -> Result<Subscriber<ipc::Service, T, ()>> {
    service?.subscriber_builder().create().map_err(ice(what))
}

/// An actor's metrics and heartbeat publisher.
pub struct MetricsPublisher {
    metrics: Publisher<ipc::Service, EpisodeReport, ()>,
    heartbeat: Publisher<ipc::Service, Heartbeat, ()>,
    key: RunKey,
}

impl MetricsPublisher {
    /// Publishers on the run's metrics and heartbeat services.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            metrics: publisher(transport.metrics_service(), "metrics publisher")?,
            heartbeat: publisher(transport.heartbeat_service(), "heartbeat publisher")?,
            key: transport.key().clone(),
        })
    }

    /// Publishes one finished episode (its `format_version`, its `pid`, this process's, and its
    /// seal are set here).
    pub fn episode(&self, metrics: EpisodeReport) -> Result<()> {
        let m = EpisodeReport {
            format_version: FORMAT_VERSION,
            pid: std::process::id(),
            ..metrics
        };
        let m = m.seal_with(&self.key, &[]);
        self.metrics.send_copy(m).map_err(ice("send metrics"))?;
        Ok(())
    }

    /// Publishes a heartbeat (its `format_version` and its seal are set here).
    pub fn heartbeat(&self, beat: Heartbeat) -> Result<()> {
        let b = Heartbeat {
            format_version: FORMAT_VERSION,
            ..beat
        };
        let b = b.seal_with(&self.key, &[]);
        self.heartbeat.send_copy(b).map_err(ice("send heartbeat"))?;
        Ok(())
    }
}

/// The replay's status publisher (history 1: a late launcher gets the last one).
pub struct StatusPublisher {
    status: Publisher<ipc::Service, ReplayStatus, ()>,
    key: RunKey,
}

impl StatusPublisher {
    /// A publisher on the run's status service.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            status: publisher(transport.status_service(), "status publisher")?,
            key: transport.key().clone(),
        })
    }

    /// Publishes the counters (its `format_version`, its `pid`, this process's, and its seal
    /// are set here).
    pub fn publish(&self, status: ReplayStatus) -> Result<()> {
        let s = ReplayStatus {
            format_version: FORMAT_VERSION,
            pid: std::process::id(),
            ..status
        };
        let s = s.seal_with(&self.key, &[]);
        self.status.send_copy(s).map_err(ice("send status"))?;
        Ok(())
    }
}

/// A subscriber to the actors' finished episodes (the launcher logs them, the learner smooths
/// their returns), each field checked against the run's bounds.
pub struct EpisodeSubscriber {
    metrics: Subscriber<ipc::Service, EpisodeReport, ()>,
    actors: usize,
    bounds: RunBounds,
    key: RunKey,
    rejects: RejectLog,
}

impl EpisodeSubscriber {
    /// Subscribes to the run's episode metrics, to be checked against `bounds`.
    pub fn new(transport: &RunTransport, bounds: RunBounds) -> Result<Self> {
        Ok(Self {
            metrics: subscriber(transport.metrics_service(), "metrics subscriber")?,
            actors: transport.actors(),
            bounds,
            key: transport.key().clone(),
            rejects: RejectLog::new("episode metrics"),
        })
    }

    /// Episode metrics received since the last call; unauthenticated, malformed and implausible
    /// ones are counted and skipped.
    pub fn episodes(&mut self) -> Result<Vec<EpisodeReport>> {
        let mut out = Vec::new();
        while let Some(s) = self.metrics.receive().map_err(ice("receive metrics"))? {
            let read = read_once(s.payload());
            match read.and_then(|m| {
                check(&m, m.format_version, &self.key, m.actor_id, self.actors)
                    .and_then(|()| check_episode(&m, &self.bounds))
                    .map(|()| m)
            }) {
                Ok(m) => out.push(m),
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(out)
    }

    /// Messages rejected as malformed or implausible.
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }

    /// Messages rejected, by reason ([`REASONS`]).
    pub fn rejected_by_reason(&self) -> [u64; REASONS.len()] {
        self.rejects.by_reason()
    }
}

/// Checks an episode report's fields against the run's bounds: finite values, 0/1 flags, steps
/// within an episode's, env steps at least the episode's, the context within the training
/// range, progress within a lap, overtakes and return within what its steps can hold.
fn check_episode(m: &EpisodeReport, bounds: &RunBounds) -> Result<(), WireError> {
    check_finite(&[m.context[0], m.context[1], m.progress, m.episode_return])?;
    check_flags(&[m.a2a, m.wall_crash, m.by_policy])?;
    if m.steps == 0 || m.steps > bounds.max_episode_steps || m.env_steps < m.steps {
        return Err(WireError::Implausible(format!(
            "an episode of {} steps at env step {} (an episode has 1 to {} steps)",
            m.steps, m.env_steps, bounds.max_episode_steps
        )));
    }
    // the context is drawn in f64 and sent in f32: allow its rounding
    let range = bounds.context_range * (1.0 + f32::EPSILON);
    for (what, c) in [("context c_v", m.context[0]), ("context c_θ", m.context[1])] {
        check_range(what, c, -range, range)?;
    }
    check_range("progress", m.progress, 0.0, MAX_PROGRESS)?;
    let steps = m.steps as f32;
    let most_overtakes = bounds.rivals as f32 * steps;
    check_range(
        "overtakes",
        m.overtakes as f32,
        -most_overtakes,
        most_overtakes,
    )?;
    let most_return = MAX_STEP_REWARD * steps;
    check_range("return", m.episode_return, -most_return, most_return)
}

/// One actor start as the launcher knows it: its process and its counters' history.
struct ActorStart {
    pid: u32,
    beats: Counter,
    episodes: Counter,
}

/// The replay start's counters' history.
struct ReplayHistory {
    /// The replay's process (0: none started yet).
    pid: u32,
    /// The count its snapshot restored, from its first status.
    restored: Option<u64>,
    /// The most it can have restored: what the replay before it had stored.
    max_restored: Option<u64>,
    inserted: Counter,
    sampled: Counter,
    batches: Counter,
    dropped: Counter,
    rejected: Counter,
}

impl ReplayHistory {
    /// A replay of `actors` actors started now as process `pid`, after one that had stored
    /// `max_restored`.
    fn new(actors: usize, max_restored: Option<u64>, pid: u32) -> Self {
        let steps = actors as f64 * MAX_ACTOR_STEPS_PER_SEC;
        Self {
            pid,
            restored: None,
            max_restored,
            inserted: Counter::new("inserted", steps),
            sampled: Counter::new("sampled", f64::INFINITY),
            batches: Counter::new("batches", f64::INFINITY),
            // a missing chunk held at least one step an actor took
            dropped: Counter::new("dropped_chunks", steps),
            rejected: Counter::new("rejected", f64::INFINITY),
        }
    }

    /// Checks a status (authenticated already) against the run's bounds and this history and
    /// takes it; one that fails changes nothing.
    fn take(&mut self, s: &ReplayStatus, bounds: &RunBounds) -> Result<(), WireError> {
        let implausible = |what: String| Err(WireError::Implausible(what));
        check_pid("replay status", s.pid, "the replay", self.pid)?;
        if s.capacity != bounds.replay_capacity || s.fill > s.capacity || s.fill > s.inserted {
            return implausible(format!(
                "replay holds {} of {} steps after {} inserted; the run's replay holds {}",
                s.fill, s.capacity, s.inserted, bounds.replay_capacity
            ));
        }
        if s.rejected
            != s.rejected_by_reason
                .iter()
                .fold(0u64, |a, &n| a.saturating_add(n))
        {
            return implausible(format!("{} rejected, not the sum by reason", s.rejected));
        }
        if s.pending_requests > MAX_PENDING_REQUESTS as u64
            || s.inserted_at_last_batch > s.inserted
            || s.batches > s.sampled
        {
            return implausible(format!(
                "{} requests pending, {} batches of {} steps, {} inserted at the last of {}",
                s.pending_requests, s.batches, s.sampled, s.inserted_at_last_batch, s.inserted
            ));
        }
        match (self.restored, self.max_restored) {
            (Some(r), _) if r != s.restored_inserts => {
                return implausible(format!(
                    "restored {} after restoring {r}",
                    s.restored_inserts
                ))
            }
            (None, Some(most)) if s.restored_inserts > most => {
                return implausible(format!(
                    "restored {}, more than the {most} stored before",
                    s.restored_inserts
                ))
            }
            _ => {}
        }
        // the first status sets where inserts continue from, once it is taken
        let mut inserted = self.inserted.clone();
        if self.restored.is_none() {
            inserted.set_base(s.restored_inserts);
        }
        let now = Instant::now();
        let counters = [
            (&mut inserted, s.inserted),
            (&mut self.sampled, s.sampled),
            (&mut self.batches, s.batches),
            (&mut self.dropped, s.dropped_chunks),
            (&mut self.rejected, s.rejected),
        ];
        for (counter, value) in counters.iter() {
            counter.check(*value, 0, now)?;
        }
        for (counter, value) in counters {
            counter.accept(value, now);
        }
        self.inserted = inserted;
        self.restored = Some(s.restored_inserts);
        Ok(())
    }
}

/// The launcher's view: episode metrics, heartbeats and replay status, each checked against the
/// run's bounds and against the history of the process start that sent it (see
/// [`actor_started`](Self::actor_started) and [`replay_started`](Self::replay_started)).
pub struct TelemetrySubscriber {
    episodes: EpisodeSubscriber,
    heartbeat: Subscriber<ipc::Service, Heartbeat, ()>,
    status: Subscriber<ipc::Service, ReplayStatus, ()>,
    bounds: RunBounds,
    key: RunKey,
    starts: Vec<Option<ActorStart>>,
    replay: ReplayHistory,
    rejects: RejectLog,
}

impl TelemetrySubscriber {
    /// Subscribes to the run's telemetry, to be checked against `bounds`.
    pub fn new(transport: &RunTransport, bounds: RunBounds) -> Result<Self> {
        Ok(Self {
            episodes: EpisodeSubscriber::new(transport, bounds)?,
            heartbeat: subscriber(transport.heartbeat_service(), "heartbeat subscriber")?,
            status: subscriber(transport.status_service(), "status subscriber")?,
            bounds,
            key: transport.key().clone(),
            starts: (0..transport.actors()).map(|_| None).collect(),
            replay: ReplayHistory::new(transport.actors(), None, 0),
            rejects: RejectLog::new("telemetry"),
        })
    }

    /// Notes that actor `id` was (re)started now as process `pid`: its counters start again,
    /// and only heartbeats of `pid` are taken from it.
    pub fn actor_started(&mut self, id: usize, pid: u32) {
        if let Some(start) = self.starts.get_mut(id) {
            *start = Some(ActorStart {
                pid,
                beats: Counter::new("heartbeat env_steps", MAX_ACTOR_STEPS_PER_SEC),
                episodes: Counter::new("episode env_steps", MAX_ACTOR_STEPS_PER_SEC),
            });
        }
    }

    /// Notes that the replay was (re)started now as process `pid`: its counters start again,
    /// from at most what the one before had stored, and only statuses of `pid` are taken.
    pub fn replay_started(&mut self, pid: u32) {
        let before = self.replay.inserted.last().or(self.replay.max_restored);
        self.replay = ReplayHistory::new(self.starts.len(), before, pid);
    }

    /// Episode metrics received since the last call; unauthenticated and malformed ones, ones
    /// of an actor not started or of another process than its current one, and ones whose env
    /// steps go back or grow faster than an actor steps are counted and skipped.
    pub fn episodes(&mut self) -> Result<Vec<EpisodeReport>> {
        let now = Instant::now();
        let mut out = Vec::new();
        for m in self.episodes.episodes()? {
            let checked = match &mut self.starts[m.actor_id as usize] {
                None => Err(not_started(m.actor_id)),
                Some(start) => check_pid("episode report", m.pid, "its actor", start.pid)
                    .and_then(|()| start.episodes.take(m.env_steps, m.steps, now)),
            };
            match checked {
                Ok(()) => out.push(m),
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(out)
    }

    /// Heartbeats received since the last call, checked once all are read against
    /// `newest_version()`, the newest weights version the caller has verified (read after the
    /// heartbeats, so that no actor can have loaded a newer one before beating): sealed with
    /// the run's key, of the actor's current process, env steps not going back nor growing faster than an actor
    /// steps, dropped steps among them, a policy version the learner has broadcast.
    pub fn heartbeats(&mut self, newest_version: impl FnOnce() -> u64) -> Result<Vec<Heartbeat>> {
        let mut beats = Vec::new();
        while let Some(s) = self.heartbeat.receive().map_err(ice("receive heartbeat"))? {
            match read_once(s.payload()) {
                Ok(beat) => beats.push(beat),
                Err(e) => self.rejects.reject(&e),
            }
        }
        let newest = newest_version();
        let now = Instant::now();
        let actors = self.starts.len();
        let mut out = Vec::new();
        for b in beats {
            let checked =
                check(&b, b.format_version, &self.key, b.actor_id, actors).and_then(|()| {
                    let start = self.starts[b.actor_id as usize]
                        .as_mut()
                        .ok_or_else(|| not_started(b.actor_id))?;
                    let fields =
                        if let Err(e) = check_pid("heartbeat", b.pid, "its actor", start.pid) {
                            Err(e)
                        } else if b.dropped_steps > b.env_steps {
                            Err(WireError::Implausible(format!(
                                "{} steps dropped of {} taken",
                                b.dropped_steps, b.env_steps
                            )))
                        } else if b.policy_version > newest {
                            Err(WireError::Implausible(format!(
                                "policy version {} is ahead of the learner's newest {newest}",
                                b.policy_version
                            )))
                        } else {
                            check_version(
                                "policy version",
                                b.policy_version,
                                self.bounds.max_policy_version,
                            )
                        };
                    fields.and_then(|()| start.beats.take(b.env_steps, 0, now))
                });
            match checked {
                Ok(()) => out.push(b),
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(out)
    }

    /// The newest replay status received since the last call that is sealed with the run's
    /// key, of the replay's current process, and fits the run's bounds and the replay start's
    /// history (counters not going back, inserts not faster than the actors step, fill within
    /// the capacity, rejections adding up).
    pub fn replay_status(&mut self) -> Result<Option<ReplayStatus>> {
        let mut newest = None;
        while let Some(s) = self.status.receive().map_err(ice("receive status"))? {
            let read = read_once(s.payload());
            match read.and_then(|st| {
                check_sealed(&st, st.format_version, &self.key, &[])
                    .and_then(|()| self.replay.take(&st, &self.bounds))
                    .map(|()| st)
            }) {
                Ok(st) => newest = Some(st),
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(newest)
    }

    /// Messages rejected as malformed or implausible.
    pub fn rejected(&self) -> u64 {
        self.rejects.count() + self.episodes.rejected()
    }

    /// Messages rejected, by reason ([`super::wire::REASONS`]).
    pub fn rejected_by_reason(&self) -> [u64; REASONS.len()] {
        let (a, b) = (self.rejects.by_reason(), self.episodes.rejects.by_reason());
        std::array::from_fn(|i| a[i] + b[i])
    }
}

/// A message of an actor whose start the launcher has not noted.
fn not_started(actor_id: u32) -> WireError {
    WireError::Implausible(format!("no start of actor {actor_id} is known"))
}

/// Checks that every flag is 0 or 1.
fn check_flags(flags: &[u32]) -> Result<(), WireError> {
    match flags.iter().position(|&f| f > 1) {
        Some(index) => Err(WireError::Value {
            index,
            value: flags[index] as f32,
        }),
        None => Ok(()),
    }
}

/// Checks that a message `what` of process `pid` comes from `whose` current process,
/// `expected`.
fn check_pid(what: &str, pid: u32, whose: &str, expected: u32) -> Result<(), WireError> {
    if pid != expected {
        return Err(WireError::Implausible(format!(
            "{what} of pid {pid}, but {whose} runs as pid {expected}"
        )));
    }
    Ok(())
}

/// Checks an actor's message `m` of format `version`: sealed with `key`, of an actor below
/// `actors`.
fn check<T: Sealed>(
    m: &T,
    version: u32,
    key: &RunKey,
    actor_id: u32,
    actors: usize,
) -> Result<(), WireError> {
    check_sealed(m, version, key, &[])?;
    if actor_id as usize >= actors {
        return Err(WireError::UnknownActor {
            got: actor_id,
            actors,
        });
    }
    Ok(())
}
