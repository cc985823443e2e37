//! Actor -> replay trajectories: the actor's chunking sender and the replay's validating receiver.

use super::bounds::check_version;
use super::shared::{check_readable, copy_slice, read_once};
use super::transport::{timed_wait, wait_until, RunTransport, Wake};
use super::wire::{
    check_sequence, new_epoch, step_stride, validate_chunk, ChunkHeader, WireError, MAX_ACT,
    MAX_CHUNK, MAX_CHUNK_FLOATS, MAX_OBS,
};
use super::{ReadStage, RejectLog};
use crate::error::{ice, IpcError, Result};
use crate::key::RunKey;
use ctxrace_config::validate::Causes;
use ctxrace_run::steps::TrajectoryStep;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::BackpressureAction;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Timeouts of a [`TrajectorySender`].
#[derive(Clone, Copy, Debug)]
pub struct SenderOptions {
    /// How long [`TrajectorySender::new`] waits for the replay to come up.
    pub handshake_timeout: Duration,
    /// How long closing waits for the replay to take the chunks still waiting, before they are
    /// dropped and counted. While running, nothing is dropped: chunks wait in the sender's
    /// backlog (see [`TrajectorySender::backlog`]) for as long as the replay needs.
    pub close_timeout: Duration,
}

impl Default for SenderOptions {
    fn default() -> Self {
        Self {
            handshake_timeout: Duration::from_secs(30),
            close_timeout: Duration::from_secs(10),
        }
    }
}

/// What a [`TrajectorySender`] did so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SenderStats {
    /// Steps delivered to the replay.
    pub sent_steps: u64,
    /// Steps dropped (still waiting for room when the sender closed).
    pub dropped_steps: u64,
    /// Chunks delivered.
    pub sent_chunks: u64,
    /// Chunks dropped.
    pub dropped_chunks: u64,
}

/// Longest sleep between two send attempts (the replay's turns wake the sender sooner).
const ATTEMPT: Duration = Duration::from_millis(10);

/// A chunk waiting for room at the replay.
struct Pending {
    header: ChunkHeader,
    floats: Vec<f32>,
}

/// An actor's end of the trajectory stream: collects steps into chunks of up to [`MAX_CHUNK`]
/// and sends them when full and at each episode's end, each sealed with the run's key and
/// carrying the sender's epoch ([`new_epoch`]), drawn when it is made.
///
/// A chunk the replay has no room for (its rate limiter holds the actors to the learner's pace,
/// or it is restarting) waits in the sender's backlog; the actor stops stepping while
/// [`backlog`](Self::backlog) is not empty and calls [`deliver`](Self::deliver) instead, so
/// nothing is dropped while the run goes on. Closing (or dropping) delivers the backlog within
/// [`SenderOptions::close_timeout`], drops and counts what is left, and then waits until the
/// replay has run a receive turn after the last send: a publisher that disappears before the
/// replay connected to it takes its unread chunks with it.
pub struct TrajectorySender {
    publisher: Publisher<ipc::Service, [f32], ChunkHeader>,
    wake: Notifier<ipc::Service>,
    turns: Listener<ipc::Service>,
    close_timeout: Duration,
    /// A chunk was delivered since the replay was last seen to take a turn.
    unconfirmed: bool,
    key: RunKey,
    header: ChunkHeader,
    buf: Vec<f32>,
    backlog: VecDeque<Pending>,
    /// Buffers of delivered chunks, reused for the next ones.
    spare: Vec<Vec<f32>>,
    stats: SenderStats,
}

impl TrajectorySender {
    /// Connects actor `actor_id` to the replay, waiting up to `opts.handshake_timeout` for the
    /// replay's subscriber (a chunk sent before it connected would be lost).
    pub fn new(
        transport: &RunTransport,
        actor_id: u32,
        obs_dim: usize,
        act_dim: usize,
        opts: SenderOptions,
    ) -> Result<Self> {
        if actor_id as usize >= transport.actors() {
            return Err(IpcError::ActorId {
                id: actor_id,
                actors: transport.actors(),
            });
        }
        if obs_dim == 0 || obs_dim > MAX_OBS || act_dim == 0 || act_dim > MAX_ACT {
            return Err(IpcError::StepDims {
                obs_dim,
                act_dim,
                max_obs: MAX_OBS,
                max_act: MAX_ACT,
            });
        }
        let ready = transport.listener(Wake::ReplayReady)?;
        let service = transport.trajectory_service(actor_id as usize)?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(MAX_CHUNK_FLOATS)
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            // a full queue returns at once: the sender then sleeps until the replay's next turn
            // instead of spinning
            .set_backpressure_handler(|_| BackpressureAction::DiscardData)
            .create()
            .map_err(ice("trajectory publisher"))?;
        wait_until(&ready, opts.handshake_timeout, transport.prefix(), || {
            service.dynamic_config().number_of_subscribers() > 0
        })?;
        Ok(Self {
            publisher,
            wake: transport.notifier(Wake::Replay)?,
            turns: ready,
            close_timeout: opts.close_timeout,
            unconfirmed: false,
            key: transport.key().clone(),
            header: ChunkHeader {
                epoch: new_epoch(),
                ..ChunkHeader::for_actor(actor_id, obs_dim, act_dim)
            },
            buf: Vec::with_capacity(MAX_CHUNK * step_stride(obs_dim, act_dim)),
            backlog: VecDeque::new(),
            spare: Vec::new(),
            stats: SenderStats::default(),
        })
    }

    /// Adds one step of episode `episode_id` acted by weights `policy_version`; sends the chunk
    /// when it is full or the episode ended. Steps of another dimension are refused with an
    /// error; values are checked by the replay.
    pub fn push(
        &mut self,
        episode_id: u64,
        policy_version: u64,
        step: &TrajectoryStep,
    ) -> Result<()> {
        let (o, a) = (self.header.obs_dim as usize, self.header.act_dim as usize);
        if step.obs.len() != o || step.action.len() != a {
            return Err(IpcError::StepSize {
                obs: step.obs.len(),
                action: step.action.len(),
                want_obs: o,
                want_action: a,
            });
        }
        if self.header.steps > 0
            && (self.header.episode_id != episode_id
                || self.header.policy_version != policy_version)
        {
            self.flush()?;
        }
        if self.header.steps == 0 {
            self.header.episode_id = episode_id;
            self.header.policy_version = policy_version;
        }
        step.encode(&mut self.buf);
        self.header.steps += 1;
        if step.is_last || self.header.steps as usize == MAX_CHUNK {
            self.flush()?;
        }
        Ok(())
    }

    /// Ends the chunk collected so far, if any, and tries to send the backlog (see
    /// [`deliver`](Self::deliver)) with one short attempt.
    pub fn flush(&mut self) -> Result<()> {
        if self.header.steps > 0 {
            let capacity = self.buf.capacity();
            let next = self
                .spare
                .pop()
                .unwrap_or_else(|| Vec::with_capacity(capacity));
            let floats = std::mem::replace(&mut self.buf, next);
            self.backlog.push_back(Pending {
                header: self.header.sealed(&self.key, &floats),
                floats,
            });
            self.header.sequence += 1;
            self.header.steps = 0;
        }
        self.deliver(Duration::ZERO)?;
        Ok(())
    }

    /// Chunks waiting for room at the replay. An actor should not step while there are any.
    pub fn backlog(&self) -> usize {
        self.backlog.len()
    }

    /// Sends the backlog, oldest first, waiting up to `wait` (at least one short attempt) for
    /// the replay to make room; returns whether the backlog is empty.
    pub fn deliver(&mut self, wait: Duration) -> Result<bool> {
        let start = Instant::now();
        while let Some(chunk) = self.backlog.front() {
            let mut sample = self
                .publisher
                .loan_slice_uninit(chunk.floats.len())
                .map_err(ice("loan chunk"))?;
            *sample.user_header_mut() = chunk.header;
            let sample = sample.write_from_slice(&chunk.floats);
            if sample.send().map_err(ice("send chunk"))? > 0 {
                self.stats.sent_steps += u64::from(chunk.header.steps);
                self.stats.sent_chunks += 1;
                self.unconfirmed = true;
                if let Some(Pending { mut floats, .. }) = self.backlog.pop_front() {
                    floats.clear();
                    self.spare.push(floats);
                }
                // A lost wake-up only delays the replay until its next timer tick.
                let _ = self.wake.notify();
                continue;
            }
            // no room (the replay's queue of this actor is full) or no replay: wait for its next
            // turn (not waking it: it has our chunks queued, and it turns when its learner asks)
            let left = wait.saturating_sub(start.elapsed());
            if left.is_zero() {
                break;
            }
            timed_wait(&self.turns, left.min(ATTEMPT), "wait for replay turn")?;
        }
        // Keep the replay's turn signals from piling up until close.
        self.turns
            .try_wait(|_| {})
            .map_err(ice("drain replay turns"))?;
        Ok(self.backlog.is_empty())
    }

    /// Counters so far.
    pub fn stats(&self) -> SenderStats {
        self.stats
    }

    /// Delivers what is left within the close timeout, drops and counts the rest, and waits
    /// until the replay has certainly connected to this sender (two replay turns after the last
    /// send); returns the counters.
    pub fn close(mut self) -> Result<SenderStats> {
        self.finish()?;
        Ok(self.stats)
    }

    fn finish(&mut self) -> Result<()> {
        self.flush()?;
        self.deliver(self.close_timeout)?;
        for chunk in self.backlog.drain(..) {
            self.stats.dropped_steps += u64::from(chunk.header.steps);
            self.stats.dropped_chunks += 1;
        }
        if !self.unconfirmed {
            return Ok(());
        }
        self.turns
            .try_wait(|_| {})
            .map_err(ice("drain replay turns"))?;
        let deadline = Instant::now() + self.close_timeout.min(Duration::from_secs(2));
        let mut turns = 0;
        while turns < 2 {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            turns += timed_wait(&self.turns, left, "wait for replay turn")?;
        }
        self.unconfirmed = false;
        Ok(())
    }
}

impl Drop for TrajectorySender {
    fn drop(&mut self) {
        if let Err(e) = self.finish() {
            tracing::warn!("closing trajectory sender: {}", Causes(&e));
        }
    }
}

/// A validated chunk as the replay receives it: a copy, out of shared memory.
#[derive(Clone, Copy, Debug)]
pub struct ChunkView<'a> {
    /// Its header.
    pub header: &'a ChunkHeader,
    /// `steps x step_stride(obs_dim, act_dim)` floats.
    pub payload: &'a [f32],
    /// Chunks of this actor are missing right before this one (or it is the actor's first one
    /// seen): the stream is not contiguous here.
    pub after_gap: bool,
}

/// The replay's end of the trajectory stream: one subscriber per actor, the actor that has
/// supplied the fewest steps served first (max-min fairness: an actor is never held back while
/// a faster one fills the buffer, however long its chunks); validates each chunk (its tag under
/// the run's key first) and tracks per-actor gaps.
///
/// Each actor's stream is at a place, the epoch and sequence number after its last accepted
/// chunk ([`check_sequence`]). Only an accepted chunk moves it: a rejected one changes nothing
/// but the counters, so no message can hold a stream up. A restarted actor's sender has a later
/// epoch, and its first chunk starts the stream again.
pub struct TrajectoryReceiver {
    services: Vec<PubSubFactory<ipc::Service, [f32], ChunkHeader>>,
    subscribers: Vec<Subscriber<ipc::Service, [f32], ChunkHeader>>,
    /// Steps taken from each actor so far.
    taken_steps: Vec<u64>,
    /// Actor ids, fewest steps taken first (re-sorted before each take).
    order: Vec<usize>,
    obs_dim: usize,
    act_dim: usize,
    key: RunKey,
    /// The place (epoch, sequence number) each actor's stream expects next.
    next_sequence: Vec<Option<(u64, u64)>>,
    /// The sequence, episode and policy version of each actor's last valid chunk, of the epoch
    /// of `next_sequence`.
    last_chunk: Vec<Option<(u64, u64, u64)>>,
    /// No chunk names weights newer than this: the learner's gradient-step target.
    max_policy_version: u64,
    missing_chunks: u64,
    /// Chunks of each actor rejected since its last valid one: the sequence numbers they took
    /// are not missing.
    rejected_since: Vec<u64>,
    /// Chunks rejected, by the actor whose stream carried them.
    rejected_by_actor: Vec<u64>,
    rejects: RejectLog,
    /// The copy of the chunk being read, reused from chunk to chunk.
    copy: Vec<f32>,
}

impl TrajectoryReceiver {
    /// Subscribes to the run's trajectories of the given dimensions, acted by weights of at most
    /// `max_policy_version`. Call [`ReplayBeacon::signal`] once every replay endpoint exists.
    pub fn new(
        transport: &RunTransport,
        obs_dim: usize,
        act_dim: usize,
        max_policy_version: u64,
    ) -> Result<Self> {
        let services = (0..transport.actors())
            .map(|id| transport.trajectory_service(id))
            .collect::<Result<Vec<_>>>()?;
        let subscribers = services
            .iter()
            .map(|s| {
                s.subscriber_builder()
                    .create()
                    .map_err(ice("trajectory subscriber"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            services,
            subscribers,
            taken_steps: vec![0; transport.actors()],
            order: (0..transport.actors()).collect(),
            obs_dim,
            act_dim,
            key: transport.key().clone(),
            next_sequence: vec![None; transport.actors()],
            last_chunk: vec![None; transport.actors()],
            max_policy_version,
            missing_chunks: 0,
            rejected_since: vec![0; transport.actors()],
            rejected_by_actor: vec![0; transport.actors()],
            rejects: RejectLog::new("trajectory chunk"),
            copy: Vec::with_capacity(MAX_CHUNK_FLOATS),
        })
    }

    /// Takes up to `max_chunks` waiting chunks, each from the actor with the fewest steps taken
    /// that has one, handing each valid one to `f`; malformed ones are counted, logged and
    /// skipped. Returns the number of chunks taken (valid or not).
    pub fn receive(&mut self, max_chunks: usize, f: impl FnMut(ChunkView)) -> Result<usize> {
        self.receive_observed(max_chunks, &mut |_| {}, f)
    }

    /// [`receive`](Self::receive), calling `hook` at each [`ReadStage`] of each chunk. Each
    /// chunk is copied out of shared memory first (into a buffer reused from chunk to chunk),
    /// then validated, and `f` sees only the copy: a chunk changed in shared memory while it is
    /// read is at worst rejected.
    pub fn receive_observed(
        &mut self,
        max_chunks: usize,
        hook: &mut dyn FnMut(ReadStage),
        mut f: impl FnMut(ChunkView),
    ) -> Result<usize> {
        let actors = self.subscribers.len();
        let mut taken = 0;
        while taken < max_chunks {
            let taken_steps = &self.taken_steps;
            self.order.sort_by_key(|&id| taken_steps[id]);
            let mut next = None;
            for &id in &self.order {
                if let Some(sample) = self.subscribers[id]
                    .receive()
                    .map_err(ice("receive chunk"))?
                {
                    next = Some((id, sample));
                    break;
                }
            }
            let Some((id, sample)) = next else {
                break;
            };
            taken += 1;
            let read = check_readable(sample.header())
                .and_then(|()| read_once(sample.user_header()))
                .and_then(|header| {
                    let payload = sample.payload();
                    if payload.len() > MAX_CHUNK_FLOATS {
                        return Err(WireError::Dims(format!(
                            "{} floats, a chunk has at most {MAX_CHUNK_FLOATS}",
                            payload.len()
                        )));
                    }
                    copy_slice(payload, &mut self.copy).map(|()| header)
                });
            hook(ReadStage::Copied);
            let header = match read {
                Ok(header) => header,
                Err(e) => {
                    // it took a sequence number, like any other malformed chunk
                    self.rejects.reject(&e);
                    self.rejected_by_actor[id] += 1;
                    self.rejected_since[id] += 1;
                    continue;
                }
            };
            let expected = &mut self.next_sequence[id];
            let place = (header.epoch, header.sequence);
            let formed = validate_chunk(
                &header,
                &self.copy,
                &self.key,
                actors,
                self.obs_dim,
                self.act_dim,
            )
            .and_then(|()| {
                if header.actor_id as usize != id {
                    return Err(WireError::WrongStream {
                        got: header.actor_id,
                        stream: id as u32,
                    });
                }
                check_version(
                    "policy version",
                    header.policy_version,
                    self.max_policy_version,
                )
            });
            let same_epoch = expected.is_some_and(|(epoch, _)| epoch == header.epoch);
            let checked = formed
                .and_then(|()| check_sequence(place, *expected))
                .and_then(|()| {
                    let last = self.last_chunk[id].filter(|_| same_epoch);
                    check_stream(&header, last)
                });
            if let Err(e) = checked {
                // the stream stays where it was
                self.rejects.reject(&e);
                self.rejected_by_actor[id] += 1;
                // a chunk going back took no new sequence number; any other rejected chunk
                // may have (its own was overwritten)
                if !matches!(e, WireError::OutOfOrder { .. }) {
                    self.rejected_since[id] += 1;
                }
                continue;
            }
            hook(ReadStage::Validated);
            let after_gap = *expected != Some(place);
            if let Some((_, next)) = expected.filter(|_| same_epoch) {
                // a rejected chunk took a sequence number: it is counted as rejected only
                let gap = header.sequence.saturating_sub(next);
                self.missing_chunks += gap.saturating_sub(self.rejected_since[id]);
            }
            self.rejected_since[id] = 0;
            *expected = Some((header.epoch, header.sequence.saturating_add(1)));
            self.last_chunk[id] = Some((header.sequence, header.episode_id, header.policy_version));
            self.taken_steps[id] += u64::from(header.steps);
            f(ChunkView {
                header: &header,
                payload: &self.copy,
                after_gap,
            });
        }
        Ok(taken)
    }

    /// Senders connected, over all actors (a killed actor's counts until its node is cleaned
    /// up).
    pub fn senders(&self) -> usize {
        self.services
            .iter()
            .map(|s| s.dynamic_config().number_of_publishers())
            .sum()
    }

    /// Chunks rejected as malformed.
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }

    /// Steps taken from each actor's valid chunks, by actor id.
    pub fn taken_steps(&self) -> &[u64] {
        &self.taken_steps
    }

    /// Chunks rejected, by the actor id of the stream that carried them.
    pub fn rejected_by_actor(&self) -> &[u64] {
        &self.rejected_by_actor
    }

    /// Chunks rejected, by reason ([`super::wire::REASONS`]).
    pub fn rejected_by_reason(&self) -> [u64; super::wire::REASONS.len()] {
        self.rejects.by_reason()
    }

    /// Chunks missing from the actors' sequence numbers (dropped by a sender), not counting
    /// the rejected ones.
    pub fn missing_chunks(&self) -> u64 {
        self.missing_chunks
    }
}

/// Checks a chunk's episode and policy version against its stream: `last` is the sequence,
/// episode and policy version of the stream's last valid chunk (`None` at its start). A chunk
/// holds steps of one episode and ends at the episode's end at the latest, and an actor loads
/// only newer weights: so episodes and versions never go back, the episode advances by at most
/// one a sequence number (it is at most the sequence number itself).
fn check_stream(header: &ChunkHeader, last: Option<(u64, u64, u64)>) -> Result<(), WireError> {
    let h = header;
    let (sequence, episode, version) = last.unwrap_or((0, 0, 0));
    for (what, got, last) in [
        ("chunk episode", h.episode_id, episode),
        ("chunk policy version", h.policy_version, version),
    ] {
        if got < last {
            return Err(WireError::Backwards { what, got, last });
        }
    }
    if h.episode_id - episode > h.sequence - sequence {
        return Err(WireError::Implausible(format!(
            "episode {} at sequence {}: a stream ends at most one episode a chunk (it was at \
             episode {episode} at sequence {sequence})",
            h.episode_id, h.sequence
        )));
    }
    Ok(())
}

/// The replay's beacon: tells waiting actors and learners that its subscribers exist, and
/// closing actors that it ran another receive turn.
pub struct ReplayBeacon {
    notifier: Notifier<ipc::Service>,
}

impl ReplayBeacon {
    /// A notifier on the run's `replay_ready` event; create it once every replay endpoint exists.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        Ok(Self {
            notifier: transport.notifier(Wake::ReplayReady)?,
        })
    }

    /// Signals readiness (on start) or the end of a receive turn (each loop turn). Never
    /// fails: a listener whose buffer is full (a stuck process) just misses this signal.
    pub fn signal(&self) {
        let _ = self.notifier.notify();
    }
}
