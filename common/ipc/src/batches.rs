//! Replay <-> learner batches. The learner publishes a [`BatchRequest`] and wakes the replay;
//! the replay answers, when its rate limiter allows, with one `[f32]` sample whose
//! [`BatchHeader`] echoes the request id, and wakes the learner. (Two publish-subscribe services
//! rather than request-response: the answer may come much later than the request, and the
//! replay serves requests from one queue whatever their origin.)

use super::transport::{timed_wait, wait_until, RunTransport, Wake};
use super::wire::{
    check_finite, validate_request, BatchHeader, BatchKind, BatchRequest, WireError, FORMAT_VERSION,
};
use super::{read_once, ReadStage, RejectLog};
use crate::error::{ice, IpcError, Result};
use ctxrace_config::batch::{sequence_floats, transition_floats};
use ctxrace_config::batch::{Batch, BatchSpec, SequenceBatch, TransitionBatch};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::time::{Duration, Instant};

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
    outstanding: Option<(u64, BatchSpec)>,
    next_id: u64,
    rejects: RejectLog,
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
        if !wait_until(&ready, handshake_timeout, || {
            service.dynamic_config().number_of_subscribers() > 0
        })? {
            return Err(IpcError::ReplayDown {
                timeout: handshake_timeout,
                prefix: transport.prefix().to_string(),
            });
        }
        Ok(Self {
            requests,
            request_service: service,
            replay_lost: false,
            batches,
            wake_replay: transport.notifier(Wake::Replay)?,
            woken,
            obs_dim,
            act_dim,
            outstanding: None,
            next_id: 0,
            rejects: RejectLog::new("batch"),
        })
    }

    /// The next batch of `spec`, waiting up to `timeout`; `None` on timeout (the request stays
    /// outstanding and a later call with the same spec waits for its answer). The replay holds
    /// requests back until its rate limiter allows sampling.
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
        let mut id = match self.outstanding {
            Some((id, s)) if s == spec => id,
            _ => match self.request(spec)? {
                Some(id) => id,
                None => return Ok(None),
            },
        };
        let deadline = Instant::now() + timeout;
        loop {
            while let Some(sample) = self.batches.receive().map_err(ice("receive batch"))? {
                let header = read_once(sample.user_header());
                if header.request_id != id {
                    continue;
                }
                self.outstanding = None;
                let copy = decode(&header, sample.payload(), spec, self.obs_dim, self.act_dim);
                hook(ReadStage::Copied);
                match copy.and_then(|batch| check_finite_batch(&batch).map(|()| batch)) {
                    Ok(batch) => {
                        hook(ReadStage::Validated);
                        return Ok(Some(batch));
                    }
                    Err(e) => {
                        self.rejects.reject(&e);
                        match self.request(spec)? {
                            Some(new) => id = new,
                            None => return Ok(None),
                        }
                    }
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            timed_wait(&self.woken, left, "wait for batch")?;
        }
    }

    /// Sends a request; `None` if no replay received it.
    fn request(&mut self, spec: BatchSpec) -> Result<Option<u64>> {
        let id = self.next_id;
        self.next_id += 1;
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
            reserved: 0,
        };
        if self
            .requests
            .send_copy(request)
            .map_err(ice("send request"))?
            == 0
        {
            self.outstanding = None;
            return Ok(None);
        }
        let _ = self.wake_replay.notify();
        self.outstanding = Some((id, spec));
        Ok(Some(id))
    }

    /// Batches rejected as malformed.
    pub fn rejected(&self) -> u64 {
        self.rejects.count()
    }
}

/// Copies the payload `p` of an answer with header `h` (a copy) into a batch of `spec`,
/// checking the header and the sizes; the values are checked on the copy afterwards
/// ([`check_finite_batch`]).
fn decode(
    h: &BatchHeader,
    p: &[f32],
    spec: BatchSpec,
    obs_dim: usize,
    act_dim: usize,
) -> Result<Batch, WireError> {
    if h.format_version != FORMAT_VERSION {
        return Err(WireError::Version {
            got: h.format_version,
        });
    }
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
        a.to_vec()
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
                obs: take(n * obs_dim),
                action: take(n * act_dim),
                reward: take(n),
                is_first: take(n),
                is_terminal: take(n),
                context: take(n * 2),
                mask: take(n * 2),
                has_mask: take(n),
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
                obs: take(batch * o),
                action: take(batch * act_dim),
                reward: take(batch),
                next_obs: take(batch * o),
                terminal: take(batch),
                context: take(batch * 2),
            }))
        }
    }
}

/// Checks that every value of a batch is finite (the error's index counts from the start of
/// the payload).
fn check_finite_batch(batch: &Batch) -> Result<(), WireError> {
    let check = |arrays: &[&[f32]]| {
        let mut offset = 0;
        for array in arrays {
            check_finite(array).map_err(|e| match e {
                WireError::Value { index, value } => WireError::Value {
                    index: offset + index,
                    value,
                },
                other => other,
            })?;
            offset += array.len();
        }
        Ok(())
    };
    match batch {
        Batch::Sequence(b) => check(&b.arrays()),
        Batch::Transition(b) => check(&b.arrays()),
    }
}

/// The replay's end: takes requests and sends batches.
pub struct BatchServer {
    requests: Subscriber<ipc::Service, BatchRequest, ()>,
    batches: Publisher<ipc::Service, [f32], BatchHeader>,
    wake_learner: Notifier<ipc::Service>,
    obs_dim: usize,
    act_dim: usize,
    max_floats: usize,
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
            rejects: RejectLog::new("batch request"),
        })
    }

    /// Takes the waiting requests; malformed ones are counted, logged and skipped.
    pub fn receive_requests(&mut self) -> Result<Vec<(BatchRequest, BatchSpec)>> {
        let mut out = Vec::new();
        while let Some(sample) = self.requests.receive().map_err(ice("receive request"))? {
            let r = read_once(sample.payload());
            match validate_request(&r, self.obs_dim, self.act_dim, self.max_floats) {
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
                Err(e) => self.rejects.reject(&e),
            }
        }
        Ok(out)
    }

    /// Sends a sequence batch answering `request_id`.
    pub fn send_sequence(&self, request_id: u64, b: &SequenceBatch) -> Result<usize> {
        let header = BatchHeader {
            format_version: FORMAT_VERSION,
            kind: BatchKind::Sequence.code(),
            request_id,
            batch: u32::try_from(b.batch)?,
            length: u32::try_from(b.length)?,
            frames: 1,
            obs_dim: u32::try_from(b.obs_dim)?,
            act_dim: u32::try_from(b.act_dim)?,
            reserved: 0,
        };
        self.send(header, &b.arrays())
    }

    /// Sends a transition batch answering `request_id`; `b.obs_dim` is `frames x` frame size.
    pub fn send_transition(
        &self,
        request_id: u64,
        frames: usize,
        b: &TransitionBatch,
    ) -> Result<usize> {
        let header = BatchHeader {
            format_version: FORMAT_VERSION,
            kind: BatchKind::Transition.code(),
            request_id,
            batch: u32::try_from(b.batch)?,
            length: 1,
            frames: u32::try_from(frames)?,
            obs_dim: u32::try_from(b.obs_dim / frames.max(1))?,
            act_dim: u32::try_from(b.act_dim)?,
            reserved: 0,
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
        *sample.user_header_mut() = header;
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
