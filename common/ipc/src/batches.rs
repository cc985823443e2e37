//! Replay <-> learner batches. The learner publishes a [`BatchRequest`] and wakes the replay;
//! the replay answers, when its rate limiter allows, with one `[f32]` sample whose
//! [`BatchHeader`] echoes the request id, and wakes the learner. (Two publish-subscribe services
//! rather than request-response: the answer may come much later than the request, and the
//! replay serves requests from one queue whatever their origin.)
//!
//! Both are sealed with the run's key. A request carries its client's epoch
//! ([`super::wire::new_epoch`]), which the answer echoes: a learner takes only answers to its
//! own outstanding request, and an answer it rejects leaves that request outstanding (it is sent
//! again at once, under the same id), so that a forged answer can neither feed the learner nor
//! make it drop the request whose real answer is on its way.

use super::shared::{check_readable, copy_slice, read_once};
use super::transport::{termination_requested, timed_wait, wait_until, RunTransport, Wake};
use super::wire::{
    check_finite, float_bytes, new_epoch, validate_request, BatchHeader, BatchKind, BatchRequest,
    Sealed as _, WireError, FORMAT_VERSION, REASONS,
};
use super::{ReadStage, RejectLog};
use crate::error::{ice, IpcError, Result};
use crate::key::RunKey;
use ctxrace_config::batch::{sequence_floats, transition_floats};
use ctxrace_config::batch::{Batch, BatchSpec, SequenceBatch, TransitionBatch};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::time::{Duration, Instant};

/// How long a request stays unanswered before the client sends it again (under the same id:
/// the replay drops a duplicate of a request it holds), and how long it waits after a refusal
/// before asking again. The replay may hold a request for its rate limiter much longer; a
/// request lost on the way, or rejected as malformed, is sent again after this.
pub const RESEND_AFTER: Duration = Duration::from_secs(2);

/// How long a request may stay unanswered before the client sends it from a new publisher. A
/// publisher whose shared memory was damaged (its allocator's state hit) can send, for good,
/// samples the replay rejects as unreadable; a new publisher has a segment of its own. A replay
/// that merely held the request that long (its rate limiter) takes the new copy as the
/// duplicate it is.
pub const RENEW_PUBLISHER_AFTER: Duration = Duration::from_secs(30);

/// A request sent and not answered yet.
#[derive(Clone, Copy, Debug)]
struct Outstanding {
    id: u64,
    spec: BatchSpec,
    sent: Instant,
    /// When this request was first sent, or its publisher last renewed: it has gone
    /// unanswered since.
    quiet_since: Instant,
}

/// What the replay answered.
enum Answer {
    Batch(Box<Batch>),
    /// A refusal, with the index of its reason in [`REASONS`].
    Refused(usize),
}

/// The learner's replay client.
pub struct ReplayClient {
    requests: Publisher<ipc::Service, BatchRequest, ()>,
    request_service: PubSubFactory<ipc::Service, BatchRequest, ()>,
    /// The replay was seen gone since the outstanding request was sent.
    replay_lost: bool,
    batches: Subscriber<ipc::Service, [f32], BatchHeader>,
    wake_replay: Notifier<ipc::Service>,
    woken: Listener<ipc::Service>,
    obs_dim: usize,
    act_dim: usize,
    key: RunKey,
    /// This client's epoch, which its requests carry and their answers echo.
    epoch: u64,
    outstanding: Option<Outstanding>,
    /// No new request for this spec before this instant, after a refusal.
    hold: Option<(BatchSpec, Instant)>,
    next_id: u64,
    resent: u64,
    renew_after: Duration,
    renewed: u64,
    rejects: RejectLog,
    refusals: RejectLog,
}

impl ReplayClient {
    /// Connects to the replay, waiting up to `handshake_timeout` for it to come up.
    pub fn new(
        transport: &RunTransport,
        obs_dim: usize,
        act_dim: usize,
        handshake_timeout: Duration,
    ) -> Result<Self> {
        let ready = transport.listener(Wake::ReplayReady)?;
        let woken = transport.listener(Wake::Learner)?;
        let batches = transport
            .batch_service()?
            .subscriber_builder()
            .create()
            .map_err(ice("batch subscriber"))?;
        let service = transport.request_service()?;
        let requests = service
            .publisher_builder()
            .create()
            .map_err(ice("request publisher"))?;
        wait_until(&ready, handshake_timeout, transport.prefix(), || {
            service.dynamic_config().number_of_subscribers() > 0
        })?;
        Ok(Self {
            requests,
            request_service: service,
            replay_lost: false,
            batches,
            wake_replay: transport.notifier(Wake::Replay)?,
            woken,
            obs_dim,
            act_dim,
            key: transport.key().clone(),
            epoch: new_epoch(),
            outstanding: None,
            hold: None,
            next_id: 0,
            resent: 0,
            renew_after: RENEW_PUBLISHER_AFTER,
            renewed: 0,
            rejects: RejectLog::new("batch"),
            refusals: RejectLog::new("batch request (the replay refused it)"),
        })
    }

    /// Renews the request publisher after `after` without an answer instead of
    /// [`RENEW_PUBLISHER_AFTER`].
    pub fn with_renew_after(mut self, after: Duration) -> Self {
        self.renew_after = after;
        self
    }

    /// The next batch of `spec`, waiting up to `timeout`; `None` on timeout (the request stays
    /// outstanding and a later call with the same spec waits for its answer, sending it again
    /// once it is [`RESEND_AFTER`] old). The replay holds requests back until its rate limiter
    /// allows sampling; a request it refuses is counted by the reason it sends back
    /// ([`refused_by_reason`](Self::refused_by_reason)) and asked again after [`RESEND_AFTER`].
    ///
    /// A replay that went away (its node cleaned up) loses the outstanding request: it is sent
    /// again once a replay is back, and `None` is returned while none is there.
    pub fn next_batch(&mut self, spec: BatchSpec, timeout: Duration) -> Result<Option<Batch>> {
        self.next_batch_observed(spec, timeout, &mut |_| {})
    }

    /// [`next_batch`](Self::next_batch), calling `hook` at each [`ReadStage`] of the answer.
    /// The answer is copied out of shared memory into the batch first, then checked, and only
    /// the copy is returned: an answer changed in shared memory while it is read is at worst
    /// rejected (and requested again).
    pub fn next_batch_observed(
        &mut self,
        spec: BatchSpec,
        timeout: Duration,
        hook: &mut dyn FnMut(ReadStage),
    ) -> Result<Option<Batch>> {
        let replay_up = self
            .request_service
            .dynamic_config()
            .number_of_subscribers()
            > 0;
        if !replay_up {
            self.replay_lost = true;
            std::thread::sleep(timeout.min(Duration::from_millis(100)));
            return Ok(None);
        }
        if std::mem::take(&mut self.replay_lost) {
            self.outstanding = None;
        }
        let deadline = Instant::now() + timeout;
        loop {
            self.ensure_request(spec)?;
            while let Some(sample) = self.batches.receive().map_err(ice("receive batch"))? {
                // an unreadable answer is rejected; its request is sent again in time
                let header = match check_readable(sample.header())
                    .and_then(|()| read_once(sample.user_header()))
                {
                    Ok(header) => header,
                    Err(e) => {
                        self.rejects.reject(&e);
                        continue;
                    }
                };
                let Some(asked) = self
                    .outstanding
                    .filter(|o| o.id == header.request_id && header.client == self.epoch)
                else {
                    continue;
                };
                let copy = decode(
                    &header,
                    sample.payload(),
                    spec,
                    &self.key,
                    self.obs_dim,
                    self.act_dim,
                );
                hook(ReadStage::Copied);
                match copy {
                    Ok(Answer::Batch(batch)) => {
                        self.outstanding = None;
                        hook(ReadStage::Validated);
                        return Ok(Some(*batch));
                    }
                    Ok(Answer::Refused(reason)) => {
                        self.outstanding = None;
                        let why = REASONS[reason];
                        self.refusals
                            .note(reason, &format!("request {}: {why}", header.request_id));
                        self.hold = Some((spec, Instant::now() + RESEND_AFTER));
                    }
                    // the request stays outstanding, its real answer still taken, and is asked
                    // again at once
                    Err(e) => {
                        self.rejects.reject(&e);
                        self.send(asked.id, asked.spec)?;
                    }
                }
                self.ensure_request(spec)?;
            }
            let now = Instant::now();
            let mut wake = deadline;
            if let Some(o) = self.outstanding {
                wake = wake.min(o.sent + RESEND_AFTER);
            } else if let Some((_, t)) = self.hold {
                wake = wake.min(t);
            }
            if now >= deadline || termination_requested() {
                return Ok(None);
            }
            timed_wait(
                &self.woken,
                wake.saturating_duration_since(now),
                "wait for batch",
            )?;
        }
    }

    /// Makes sure a request for `spec` is on its way: the outstanding one, sent again once it
    /// is [`RESEND_AFTER`] old, or a new one (not within [`RESEND_AFTER`] of a refusal of
    /// `spec`).
    fn ensure_request(&mut self, spec: BatchSpec) -> Result<()> {
        let now = Instant::now();
        match self.outstanding {
            Some(o) if o.spec == spec => {
                if now.saturating_duration_since(o.sent) >= RESEND_AFTER {
                    self.resent += 1;
                    if self.resent <= 10 || self.resent.is_multiple_of(1000) {
                        tracing::info!(
                            "batch request {} unanswered for {RESEND_AFTER:?}: sent again ({} so far)",
                            o.id,
                            self.resent
                        );
                    }
                    if now.saturating_duration_since(o.quiet_since) >= self.renew_after {
                        self.renew_publisher(o.id)?;
                    }
                    self.send(o.id, spec)?;
                }
            }
            _ if self.hold.is_some_and(|(s, t)| s == spec && now < t) => {}
            _ => {
                let id = self.next_id;
                self.next_id += 1;
                self.send(id, spec)?;
            }
        }
        Ok(())
    }

    /// Replaces the request publisher by a new one (request `id` has gone unanswered for
    /// `renew_after`), dropping the old one once the new one exists. The request's quiet time
    /// counts again from its next sending.
    fn renew_publisher(&mut self, id: u64) -> Result<()> {
        self.requests = self
            .request_service
            .publisher_builder()
            .create()
            .map_err(ice("request publisher"))?;
        self.renewed += 1;
        if let Some(o) = &mut self.outstanding {
            o.quiet_since = Instant::now();
        }
        if self.renewed <= 10 || self.renewed.is_multiple_of(100) {
            tracing::info!(
                "batch request {id} unanswered for {:?}: sent from a new publisher ({} so far; \
                 the replay may have been unable to read the old one's shared memory)",
                self.renew_after,
                self.renewed
            );
        }
        Ok(())
    }

    /// Sends request `id` for `spec`; it is outstanding if a replay received it (unanswered
    /// since its first sending if it was outstanding already).
    fn send(&mut self, id: u64, spec: BatchSpec) -> Result<()> {
        let (kind, batch, length, frames) = match spec {
            BatchSpec::Sequence { batch, length } => (BatchKind::Sequence, batch, length, 1),
            BatchSpec::Transition {
                batch,
                frames,
                reward_delay,
            } => (BatchKind::Transition, batch, 1 + reward_delay, frames),
        };
        let request = BatchRequest {
            format_version: FORMAT_VERSION,
            kind: kind.code(),
            request_id: id,
            batch: u32::try_from(batch)?,
            length: u32::try_from(length)?,
            frames: u32::try_from(frames)?,
            client: self.epoch,
            ..BatchRequest::default()
        }
        .seal_with(&self.key, &[]);
        let reached = self
            .requests
            .send_copy(request)
            .map_err(ice("send request"))?;
        let now = Instant::now();
        let quiet_since = match self.outstanding {
            Some(o) if o.id == id && o.spec == spec => o.quiet_since,
            _ => now,
        };
        self.outstanding = (reached > 0).then_some(Outstanding {
            id,
            spec,
            sent: now,
            quiet_since,
        });
        let _ = self.wake_replay.notify();
        Ok(())
    }

    /// Batches rejected as malformed.
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }

    /// Answers rejected, by reason ([`REASONS`]).
    pub fn rejected_by_reason(&self) -> [u64; REASONS.len()] {
        self.rejects.by_reason()
    }

    /// Requests the replay refused, by the reason it sent back ([`REASONS`]).
    pub fn refused_by_reason(&self) -> [u64; REASONS.len()] {
        self.refusals.by_reason()
    }

    /// Requests sent again after [`RESEND_AFTER`] without an answer.
    pub fn resent(&self) -> u64 {
        self.resent
    }

    /// Request publishers replaced after [`RENEW_PUBLISHER_AFTER`] without an answer.
    pub fn publishers_renewed(&self) -> u64 {
        self.renewed
    }
}

/// Reads the answer with header `h` (a copy) and payload `p` (in shared memory): a refusal and
/// its reason, or a batch of `spec` copied out of `p`, whose seal under `key` and values are
/// checked on the copy.
fn decode(
    h: &BatchHeader,
    p: &[f32],
    spec: BatchSpec,
    key: &RunKey,
    obs_dim: usize,
    act_dim: usize,
) -> Result<Answer, WireError> {
    if h.format_version != FORMAT_VERSION {
        return Err(WireError::Version {
            got: h.format_version,
        });
    }
    let checksum = |parts: &[&[f32]]| {
        let bytes: Vec<&[u8]> = parts.iter().map(|part| float_bytes(part)).collect();
        h.check_with(key, &bytes)
    };
    if h.refused != 0 {
        checksum(&[])?;
        return match (h.refused as usize - 1, p.len()) {
            (reason, 0) if reason < REASONS.len() => Ok(Answer::Refused(reason)),
            _ => Err(WireError::Dims(format!(
                "a refusal with code {} and {} floats",
                h.refused,
                p.len()
            ))),
        };
    }
    let batch = copy_batch(h, p, spec, obs_dim, act_dim)?;
    match &batch {
        Batch::Sequence(b) => checksum(&b.arrays())?,
        Batch::Transition(b) => checksum(&b.arrays())?,
    }
    check_batch_values(&batch)?;
    Ok(Answer::Batch(Box::new(batch)))
}

/// Copies the payload `p` of an answer with header `h` into a batch of `spec`, checking the
/// header's kind and sizes.
fn copy_batch(
    h: &BatchHeader,
    p: &[f32],
    spec: BatchSpec,
    obs_dim: usize,
    act_dim: usize,
) -> Result<Batch, WireError> {
    if h.obs_dim as usize != obs_dim || h.act_dim as usize != act_dim {
        return Err(WireError::Dims(format!(
            "batch has obs_dim {} act_dim {}, learner expects {obs_dim} and {act_dim}",
            h.obs_dim, h.act_dim
        )));
    }
    let mut rest = p;
    let mut take = |n: usize| {
        let (a, b) = rest.split_at(n);
        rest = b;
        let mut copy = Vec::new();
        copy_slice(a, &mut copy).map(|()| copy)
    };
    let bad = || WireError::Dims(format!("batch payload of {} floats for {spec:?}", p.len()));
    match spec {
        BatchSpec::Sequence { batch, length } => {
            let ok = h.kind == BatchKind::Sequence.code()
                && h.batch as usize == batch
                && h.length as usize == length
                && Some(p.len()) == sequence_floats(batch, length, obs_dim, act_dim);
            if !ok {
                return Err(bad());
            }
            let n = batch * length;
            Ok(Batch::Sequence(SequenceBatch {
                batch,
                length,
                obs_dim,
                act_dim,
                obs: take(n * obs_dim)?,
                action: take(n * act_dim)?,
                reward: take(n)?,
                is_first: take(n)?,
                is_terminal: take(n)?,
                context: take(n * 2)?,
                mask: take(n * 2)?,
                has_mask: take(n)?,
            }))
        }
        BatchSpec::Transition { batch, frames, .. } => {
            let ok = h.kind == BatchKind::Transition.code()
                && h.batch as usize == batch
                && h.frames as usize == frames
                && Some(p.len()) == transition_floats(batch, frames, obs_dim, act_dim);
            if !ok {
                return Err(bad());
            }
            let o = frames * obs_dim;
            Ok(Batch::Transition(TransitionBatch {
                batch,
                obs_dim: o,
                act_dim,
                obs: take(batch * o)?,
                action: take(batch * act_dim)?,
                reward: take(batch)?,
                next_obs: take(batch * o)?,
                terminal: take(batch)?,
                context: take(batch * 2)?,
            }))
        }
    }
}

/// Checks the values of a batch: every one finite, flags 0 or 1, cMask's masks in `[0, 1]`
/// (the error's index counts from the start of the payload).
fn check_batch_values(batch: &Batch) -> Result<(), WireError> {
    let (arrays, flags, unit) = match batch {
        // obs, action, reward, is_first, is_terminal, context, mask, has_mask
        Batch::Sequence(b) => (b.arrays().to_vec(), vec![3, 4, 7], vec![6]),
        // obs, action, reward, next_obs, terminal, context
        Batch::Transition(b) => (b.arrays().to_vec(), vec![4], vec![]),
    };
    let mut offset = 0;
    for (k, array) in arrays.iter().enumerate() {
        let at = |index: usize| WireError::Value {
            index: offset + index,
            value: array[index],
        };
        check_finite(array).map_err(|e| match e {
            WireError::Value { index, .. } => at(index),
            other => other,
        })?;
        let bad = if flags.contains(&k) {
            array.iter().position(|&v| v != 0.0 && v != 1.0)
        } else if unit.contains(&k) {
            array.iter().position(|v| !(0.0..=1.0).contains(v))
        } else {
            None
        };
        if let Some(index) = bad {
            return Err(at(index));
        }
        offset += array.len();
    }
    Ok(())
}

/// The replay's end: takes requests and sends batches.
pub struct BatchServer {
    requests: Subscriber<ipc::Service, BatchRequest, ()>,
    batches: Publisher<ipc::Service, [f32], BatchHeader>,
    wake_learner: Notifier<ipc::Service>,
    obs_dim: usize,
    act_dim: usize,
    max_floats: usize,
    key: RunKey,
    rejects: RejectLog,
}

impl BatchServer {
    /// Serves batches of up to `max_floats` floats of the given dimensions. Call
    /// [`super::ReplayBeacon::signal`] once every replay endpoint exists.
    pub fn new(
        transport: &RunTransport,
        obs_dim: usize,
        act_dim: usize,
        max_floats: usize,
    ) -> Result<Self> {
        let requests = transport
            .request_service()?
            .subscriber_builder()
            .create()
            .map_err(ice("request subscriber"))?;
        let batches = transport
            .batch_service()?
            .publisher_builder()
            .initial_max_slice_len(max_floats)
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(1)
            .create()
            .map_err(ice("batch publisher"))?;
        Ok(Self {
            requests,
            batches,
            wake_learner: transport.notifier(Wake::Learner)?,
            obs_dim,
            act_dim,
            max_floats,
            key: transport.key().clone(),
            rejects: RejectLog::new("batch request"),
        })
    }

    /// Takes the waiting requests; malformed ones are counted, logged and answered with a
    /// refusal saying why ([`refuse`](Self::refuse)), except those whose checksum or tag fails:
    /// nothing in them can be trusted, their id included (a real one is sent again in time).
    pub fn receive_requests(&mut self) -> Result<Vec<(BatchRequest, BatchSpec)>> {
        let mut out = Vec::new();
        while let Some(sample) = self.requests.receive().map_err(ice("receive request"))? {
            let r = match read_once(sample.payload()) {
                Ok(r) => r,
                Err(e) => {
                    // no request id to refuse: its learner sends it again in time
                    self.rejects.reject(&e);
                    continue;
                }
            };
            match validate_request(&r, &self.key, self.obs_dim, self.act_dim, self.max_floats) {
                Ok(BatchKind::Sequence) => out.push((
                    r,
                    BatchSpec::Sequence {
                        batch: r.batch as usize,
                        length: r.length as usize,
                    },
                )),
                Ok(BatchKind::Transition) => out.push((
                    r,
                    BatchSpec::Transition {
                        batch: r.batch as usize,
                        frames: r.frames as usize,
                        reward_delay: r.length as usize - 1,
                    },
                )),
                Err(e) => {
                    self.rejects.reject(&e);
                    if !matches!(e, WireError::Checksum { .. } | WireError::Unauthenticated) {
                        self.refuse(&r, e.reason())?;
                    }
                }
            }
        }
        Ok(out)
    }

    /// Answers `request` with a refusal for the reason of index `reason`
    /// ([`super::wire::REASONS`]), so that its learner counts it and asks again later.
    pub fn refuse(&self, request: &BatchRequest, reason: usize) -> Result<usize> {
        let header = BatchHeader {
            refused: reason as u32 + 1,
            ..BatchHeader::answering(request)
        };
        self.send(header, &[])
    }

    /// Sends a sequence batch answering `request`.
    pub fn send_sequence(&self, request: &BatchRequest, b: &SequenceBatch) -> Result<usize> {
        let header = BatchHeader {
            kind: BatchKind::Sequence.code(),
            batch: u32::try_from(b.batch)?,
            length: u32::try_from(b.length)?,
            frames: 1,
            obs_dim: u32::try_from(b.obs_dim)?,
            act_dim: u32::try_from(b.act_dim)?,
            ..BatchHeader::answering(request)
        };
        self.send(header, &b.arrays())
    }

    /// Sends a transition batch answering `request`; `b.obs_dim` is `frames x` frame size.
    pub fn send_transition(
        &self,
        request: &BatchRequest,
        frames: usize,
        b: &TransitionBatch,
    ) -> Result<usize> {
        let header = BatchHeader {
            kind: BatchKind::Transition.code(),
            batch: u32::try_from(b.batch)?,
            length: 1,
            frames: u32::try_from(frames)?,
            obs_dim: u32::try_from(b.obs_dim / frames.max(1))?,
            act_dim: u32::try_from(b.act_dim)?,
            ..BatchHeader::answering(request)
        };
        self.send(header, &b.arrays())
    }

    fn send(&self, header: BatchHeader, parts: &[&[f32]]) -> Result<usize> {
        let len: usize = parts.iter().map(|p| p.len()).sum();
        if len > self.max_floats {
            return Err(IpcError::BatchTooLarge {
                len,
                max: self.max_floats,
            });
        }
        let mut sample = self
            .batches
            .loan_slice_uninit(len)
            .map_err(ice("loan batch"))?;
        *sample.user_header_mut() = header.sealed(&self.key, parts);
        let mut offset = 0;
        let slots = sample.payload_mut();
        for part in parts {
            for (slot, v) in slots[offset..offset + part.len()]
                .iter_mut()
                .zip(part.iter())
            {
                slot.write(*v);
            }
            offset += part.len();
        }
        // SAFETY: the loop above wrote all `len` elements.
        let sample = unsafe { sample.assume_init() };
        let reached = sample.send().map_err(ice("send batch"))?;
        let _ = self.wake_learner.notify();
        Ok(reached)
    }

    /// Requests rejected as malformed.
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }

    /// Requests rejected, by reason ([`super::wire::REASONS`]).
    pub fn rejected_by_reason(&self) -> [u64; super::wire::REASONS.len()] {
        self.rejects.by_reason()
    }
}
