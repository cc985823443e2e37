//! Fault injection: raw senders that put any header and payload on a live run's real services,
//! bypassing every check a well-behaved sender makes, so that tests (and tools probing a run)
//! can show that each kind of malformed message is rejected, counted under its reason, and
//! harms nothing else. Messages go out as they are given: seal them ([`super::wire::Sealed`])
//! with the run's key to reach the readers' checks after the tag (a faulty process of the
//! run), or with another key to play a process that can write the run's shared memory but does
//! not hold its key (`unauthenticated`).
//!
//! A message can also be kept [`Held`] after it was sent and rewritten in shared memory while
//! a receiver holds it, as a faulty or hostile process could: with the receivers' `*_observed`
//! reads (see [`super::ReadStage`]) a test rewrites it at a chosen point of the read.
//!
//! The publishers live as long as the [`Injector`]: a publisher that disappears before its
//! subscribers connected to it takes its unread messages with it. Its weights and batch
//! publishers take the slots a restarting learner and replay would use, so inject while they
//! run.

use super::telemetry::publisher;
use super::transport::{RunTransport, Wake};
use super::wire::{
    BatchHeader, BatchRequest, ChunkHeader, EpisodeReport, Heartbeat, ReplayStatus, WeightsHeader,
    MAX_CHUNK_FLOATS,
};
use crate::error::{ice, IpcError, Result};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use std::marker::PhantomData;
use std::ptr::NonNull;

/// Largest weights blob an [`Injector`] sends.
const MAX_WEIGHTS: usize = 4096;
/// Largest batch an [`Injector`] sends, in floats.
const MAX_BATCH_FLOATS: usize = 1 << 16;

/// Raw publishers on every service a run's processes receive on.
pub struct Injector {
    chunks: Vec<Publisher<ipc::Service, [f32], ChunkHeader>>,
    requests: Publisher<ipc::Service, BatchRequest, ()>,
    weights: Publisher<ipc::Service, [u8], WeightsHeader>,
    batches: Publisher<ipc::Service, [f32], BatchHeader>,
    episodes: Publisher<ipc::Service, EpisodeReport, ()>,
    heartbeats: Publisher<ipc::Service, Heartbeat, ()>,
    status: Publisher<ipc::Service, ReplayStatus, ()>,
    wake_replay: Notifier<ipc::Service>,
    wake_actors: Notifier<ipc::Service>,
    wake_learner: Notifier<ipc::Service>,
}

impl Injector {
    /// Publishers on the services of the run `transport` joined.
    pub fn new(transport: &RunTransport) -> Result<Self> {
        let chunks = (0..transport.actors())
            .map(|id| {
                transport
                    .trajectory_service(id)?
                    .publisher_builder()
                    .initial_max_slice_len(MAX_CHUNK_FLOATS)
                    .max_loaned_samples(1)
                    .create()
                    .map_err(ice("injected chunk publisher"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            chunks,
            requests: publisher(transport.request_service(), "injected request publisher")?,
            weights: transport
                .weights_service()?
                .publisher_builder()
                .initial_max_slice_len(MAX_WEIGHTS)
                .max_loaned_samples(1)
                .create()
                .map_err(ice("injected weights publisher"))?,
            batches: transport
                .batch_service()?
                .publisher_builder()
                .initial_max_slice_len(MAX_BATCH_FLOATS)
                .max_loaned_samples(1)
                .create()
                .map_err(ice("injected batch publisher"))?,
            episodes: publisher(transport.metrics_service(), "injected metrics publisher")?,
            heartbeats: publisher(
                transport.heartbeat_service(),
                "injected heartbeat publisher",
            )?,
            status: publisher(transport.status_service(), "injected status publisher")?,
            wake_replay: transport.notifier(Wake::Replay)?,
            wake_actors: transport.notifier(Wake::Actors)?,
            wake_learner: transport.notifier(Wake::Learner)?,
        })
    }

    /// Sends `header` and `payload` (at most [`MAX_CHUNK_FLOATS`] floats) on the trajectory
    /// service of actor `stream`; returns the subscribers reached.
    pub fn chunk(&self, stream: usize, header: ChunkHeader, payload: &[f32]) -> Result<usize> {
        Ok(self.chunk_held(stream, header, payload)?.reached)
    }

    /// [`chunk`](Self::chunk), keeping the sent chunk to rewrite.
    pub fn chunk_held(
        &self,
        stream: usize,
        header: ChunkHeader,
        payload: &[f32],
    ) -> Result<Held<'_, f32, ChunkHeader>> {
        let publisher = self.chunks.get(stream).ok_or(IpcError::NoStream(stream))?;
        send_slice(publisher, header, payload, &self.wake_replay)
    }

    /// Sends `header` and `payload` (at most 64 Ki floats) on the batch service, as the replay
    /// answers a request; keeps the sent batch to rewrite.
    pub fn batch_held(
        &self,
        header: BatchHeader,
        payload: &[f32],
    ) -> Result<Held<'_, f32, BatchHeader>> {
        if payload.len() > MAX_BATCH_FLOATS {
            return Err(IpcError::InjectedTooLarge {
                what: "batches",
                max: MAX_BATCH_FLOATS,
                unit: "floats",
            });
        }
        send_slice(&self.batches, header, payload, &self.wake_learner)
    }

    /// Sends a batch request as it is.
    pub fn request(&self, request: BatchRequest) -> Result<usize> {
        let reached = self
            .requests
            .send_copy(request)
            .map_err(ice("send injected request"))?;
        let _ = self.wake_replay.notify();
        Ok(reached)
    }

    /// Broadcasts `header` with `bytes` (at most 4 KiB) on the weights service.
    pub fn weights(&self, header: WeightsHeader, bytes: &[u8]) -> Result<usize> {
        Ok(self.weights_held(header, bytes)?.reached)
    }

    /// [`weights`](Self::weights), keeping the sent blob to rewrite.
    pub fn weights_held(
        &self,
        header: WeightsHeader,
        bytes: &[u8],
    ) -> Result<Held<'_, u8, WeightsHeader>> {
        if bytes.len() > MAX_WEIGHTS {
            return Err(IpcError::InjectedTooLarge {
                what: "weights",
                max: MAX_WEIGHTS,
                unit: "bytes",
            });
        }
        send_slice(&self.weights, header, bytes, &self.wake_actors)
    }

    /// Publishes episode metrics as they are.
    pub fn episode(&self, metrics: EpisodeReport) -> Result<usize> {
        self.episodes
            .send_copy(metrics)
            .map_err(ice("send injected metrics"))
    }

    /// Publishes a heartbeat as it is.
    pub fn heartbeat(&self, beat: Heartbeat) -> Result<usize> {
        self.heartbeats
            .send_copy(beat)
            .map_err(ice("send injected heartbeat"))
    }

    /// Publishes a replay status as it is.
    pub fn status(&self, status: ReplayStatus) -> Result<usize> {
        self.status
            .send_copy(status)
            .map_err(ice("send injected status"))
    }
}

/// A message an [`Injector`] sent, still writable in its publisher's shared memory: the
/// receivers see every rewrite of a message they have not released yet. It lives no longer than
/// its injector, whose publisher keeps the memory mapped.
pub struct Held<'a, T, H> {
    /// Subscribers the message reached.
    pub reached: usize,
    header: NonNull<H>,
    payload: NonNull<T>,
    len: usize,
    injector: PhantomData<&'a Injector>,
}

impl<T: Copy, H: Copy> Held<'_, T, H> {
    /// Rewrites the header.
    pub fn set_header(&self, header: H) {
        // SAFETY: `header` points at the header of a sample of a publisher that lives as long as
        // the injector this borrows: the memory stays mapped, writable by this process and
        // aligned for H, whose every bit pattern a plain wire struct accepts.
        unsafe { std::ptr::write_volatile(self.header.as_ptr(), header) }
    }

    /// Rewrites the payload's element `index`.
    pub fn set(&self, index: usize, value: T) -> Result<()> {
        if index >= self.len {
            return Err(IpcError::Element {
                index,
                len: self.len,
            });
        }
        // SAFETY: as in `set_header`; `index` is within the sample's `len` elements.
        unsafe { std::ptr::write_volatile(self.payload.as_ptr().add(index), value) };
        Ok(())
    }
}

/// Sends one sample of `header` and `payload` and wakes whoever `wake` wakes; returns it held.
fn send_slice<'a, T, H>(
    publisher: &'a Publisher<ipc::Service, [T], H>,
    header: H,
    payload: &[T],
    wake: &Notifier<ipc::Service>,
) -> Result<Held<'a, T, H>>
where
    T: std::fmt::Debug + ZeroCopySend + Copy + 'static,
    H: std::fmt::Debug + ZeroCopySend + Default + 'static,
{
    let len = payload.len();
    let mut sample = publisher
        .loan_slice_uninit(len)
        .map_err(ice("loan injected sample"))?;
    *sample.user_header_mut() = header;
    let header = NonNull::from(sample.user_header_mut());
    let mut sample = sample.write_from_slice(payload);
    let payload = NonNull::from(sample.payload_mut()).cast::<T>();
    let reached = sample.send().map_err(ice("send injected sample"))?;
    let _ = wake.notify();
    Ok(Held {
        reached,
        header,
        payload,
        len,
        injector: PhantomData,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::{step_stride, BatchKind, Sealed as _};
    use crate::RunKey;
    use crate::{
        BatchServer, Isolated, ReadStage, ReplayClient, TrajectoryReceiver, WeightsReceiver,
    };
    use ctxrace_config::batch::{Batch, BatchSpec, SequenceBatch};
    use std::time::Duration;

    const OBS: usize = 3;
    const ACT: usize = 2;

    /// When a test rewrites a held message: right after it was sent (before the reader copies
    /// it), or at one of the reader's stages.
    #[derive(Clone, Copy, Debug, PartialEq)]
    enum When {
        BeforeRead,
        At(ReadStage),
    }

    const WHEN: [When; 3] = [
        When::BeforeRead,
        When::At(ReadStage::Copied),
        When::At(ReadStage::Validated),
    ];

    /// A hook that calls `rewrite` once, at `when`'s stage.
    fn rewrite_at(when: When, mut rewrite: impl FnMut()) -> impl FnMut(ReadStage) {
        move |stage| {
            if when == When::At(stage) {
                rewrite();
            }
        }
    }

    #[test]
    fn chunks_rewritten_in_shared_memory_are_stored_as_validated_or_rejected() {
        let isolated = Isolated::new("inject-chunks");
        let t = RunTransport::open(&isolated.0, 2, "replay", &crate::test_key()).unwrap();
        let mut rx = TrajectoryReceiver::new(&t, OBS, ACT, 10).unwrap();
        let inject = Injector::new(&t).unwrap();
        let stride = step_stride(OBS, ACT);
        let steps = 4;
        let payload: Vec<f32> = (0..steps * stride)
            .map(|i| if i % stride < OBS { i as f32 } else { 0.0 })
            .collect();
        let reward = OBS + ACT;
        // the rejected chunk between two valid ones: its sequence number must not count as
        // missing
        let order = [WHEN[1], WHEN[0], WHEN[2]];
        for (sequence, when) in order.into_iter().enumerate() {
            let header = ChunkHeader {
                sequence: sequence as u64,
                steps: steps as u32,
                ..ChunkHeader::for_actor(0, OBS, ACT)
            }
            .sealed(&crate::test_key(), &payload);
            let held = inject.chunk_held(0, header, &payload).unwrap();
            assert_eq!(held.reached, 1);
            // an actor id, dimensions and a step count that would index out of bounds, and a
            // NaN reward
            let rewrite = || {
                held.set_header(ChunkHeader {
                    actor_id: 9,
                    obs_dim: 200,
                    steps: 64,
                    ..header
                });
                held.set(reward, f32::NAN).unwrap();
            };
            if when == When::BeforeRead {
                // the second rewrite must not be what made it fail: only the NaN
                held.set(reward, f32::NAN).unwrap();
            }
            let mut stored = Vec::new();
            let mut hook = rewrite_at(when, rewrite);
            let taken = rx
                .receive_observed(1, &mut hook, |c| {
                    stored.push((*c.header, c.payload.to_vec()))
                })
                .unwrap();
            assert_eq!(taken, 1, "{when:?}");
            if when == When::BeforeRead {
                assert!(stored.is_empty(), "{when:?}: {stored:?}");
                assert_eq!(rx.rejected(), 1);
            } else {
                assert_eq!(stored, vec![(header, payload.clone())], "{when:?}");
            }
        }
        assert_eq!(rx.rejected(), 1);
        // the rejected chunk's sequence number is not counted as missing too
        assert_eq!(rx.missing_chunks(), 0);
    }

    /// A key other than the run's: what a process without the run's key seals with (its
    /// CRC-32 is right, its tag is not).
    fn forger() -> RunKey {
        RunKey::from_bytes([3; crate::KEY_LEN])
    }

    /// Issue 47's first poisoned value: a chunk whose sequence is rewritten to 2^63 in shared
    /// memory fails its checksum; written with a matching checksum by a process without the
    /// run's key it fails its tag; either way the actor's stream goes on from where it was. A
    /// chunk (sealed with the run's key, as by a faulty actor) naming weights beyond the run's
    /// target, an episode going back or jumping ahead of its sequence is rejected too.
    #[test]
    fn a_rewritten_or_forged_chunk_is_rejected_and_does_not_stop_the_stream() {
        let isolated = Isolated::new("inject-sequence");
        let t = RunTransport::open(&isolated.0, 1, "replay", &crate::test_key()).unwrap();
        let mut rx = TrajectoryReceiver::new(&t, OBS, ACT, 10).unwrap();
        let inject = Injector::new(&t).unwrap();
        let (key, forger) = (crate::test_key(), forger());
        let payload = vec![0.0; step_stride(OBS, ACT)];
        let header = |sequence, episode_id, policy_version| ChunkHeader {
            sequence,
            episode_id,
            policy_version,
            steps: 1,
            epoch: 5,
            ..ChunkHeader::for_actor(0, OBS, ACT)
        };
        let mut stored = Vec::new();
        for sequence in 0..10 {
            let episode = sequence / 2;
            let good = header(sequence, episode, sequence).sealed(&key, &payload);
            let held = inject.chunk_held(0, good, &payload).unwrap();
            let forged = match sequence {
                2 => Some(ChunkHeader {
                    sequence: 1 << 63,
                    ..good
                }),
                3 => Some(header(1 << 63, episode, sequence).sealed(&forger, &payload)),
                5 => Some(header(sequence, episode, 11).sealed(&key, &payload)),
                6 => Some(header(sequence, 0, sequence).sealed(&key, &payload)),
                7 => Some(header(sequence, 1 << 40, sequence).sealed(&key, &payload)),
                _ => None,
            };
            if let Some(forged) = forged {
                held.set_header(forged);
            }
            assert_eq!(
                rx.receive(1, |c| stored.push(c.header.sequence)).unwrap(),
                1
            );
        }
        // each poisoned chunk took its sequence number: the stream is contiguous after them
        assert_eq!(stored, vec![0, 1, 4, 8, 9]);
        let by = crate::wire::named_reasons(&rx.rejected_by_reason());
        let want = [
            ("checksum", 1),
            ("unauthenticated", 1),
            ("implausible", 2),
            ("backwards", 1),
        ];
        assert_eq!(by, want.into_iter().collect());
        assert_eq!(rx.missing_chunks(), 0);
    }

    /// Chunks forged far ahead of their stream (sequence 50,000, 2^63, 2^64-1, with a valid
    /// CRC-32, in the actor's epoch and a later one) are rejected as unauthenticated and move
    /// nothing: every real chunk after them is taken. (With the CRC-32 alone, one such chunk
    /// was taken and held the stream up for three real ones.)
    #[test]
    fn chunks_forged_ahead_of_their_stream_do_not_shift_it() {
        let isolated = Isolated::new("inject-ahead");
        let t = RunTransport::open(&isolated.0, 1, "replay", &crate::test_key()).unwrap();
        let mut rx = TrajectoryReceiver::new(&t, OBS, ACT, 100).unwrap();
        let inject = Injector::new(&t).unwrap();
        let payload = vec![0.0; step_stride(OBS, ACT)];
        let chunk = |key: &RunKey, epoch, sequence| {
            ChunkHeader {
                sequence,
                steps: 1,
                epoch,
                ..ChunkHeader::for_actor(0, OBS, ACT)
            }
            .sealed(key, &payload)
        };
        let mut stored = Vec::new();
        for sequence in 0..12 {
            if sequence == 5 {
                for (epoch, forged) in [(7, 50_000), (7, 1 << 63), (8, u64::MAX), (u64::MAX, 0)] {
                    inject
                        .chunk(0, chunk(&forger(), epoch, forged), &payload)
                        .unwrap();
                }
            }
            inject
                .chunk(0, chunk(&crate::test_key(), 7, sequence), &payload)
                .unwrap();
            rx.receive(8, |c| stored.push(c.header.sequence)).unwrap();
        }
        assert_eq!(stored, (0..12).collect::<Vec<_>>());
        let by = crate::wire::named_reasons(&rx.rejected_by_reason());
        assert_eq!(by, [("unauthenticated", 4)].into_iter().collect());
        assert_eq!(rx.missing_chunks(), 0);
    }

    /// Copies of real chunks sent again (by a process that read them in shared memory): in
    /// the stream they were taken from they go back and are rejected; a restarted actor's
    /// stream (a later epoch) takes over, and copies of its predecessor's chunks go back too;
    /// and a restarted replay that takes an old copy first still takes every real chunk after
    /// it: no copy locks a stream out.
    #[test]
    fn replayed_copies_of_real_chunks_never_lock_a_stream_out() {
        let isolated = Isolated::new("inject-replayed");
        let key = crate::test_key();
        let t = RunTransport::open(&isolated.0, 1, "replay", &key).unwrap();
        let mut rx = TrajectoryReceiver::new(&t, OBS, ACT, 100).unwrap();
        let inject = Injector::new(&t).unwrap();
        let payload = vec![0.0; step_stride(OBS, ACT)];
        let chunk = |epoch, sequence| {
            ChunkHeader {
                sequence,
                steps: 1,
                epoch,
                ..ChunkHeader::for_actor(0, OBS, ACT)
            }
            .sealed(&key, &payload)
        };
        let take = |rx: &mut TrajectoryReceiver, sent: &[ChunkHeader]| {
            let mut stored = Vec::new();
            for &h in sent {
                inject.chunk(0, h, &payload).unwrap();
                rx.receive(1, |c| stored.push((c.header.epoch, c.header.sequence)))
                    .unwrap();
            }
            stored
        };
        let first: Vec<ChunkHeader> = (0..4).map(|s| chunk(10, s)).collect();
        // the first sender's chunks, a copy of its first and of its newest
        let sent = [&first[..], &[first[0], first[3]]].concat();
        assert_eq!(
            take(&mut rx, &sent),
            vec![(10, 0), (10, 1), (10, 2), (10, 3)]
        );
        // the actor restarted (epoch 20): its stream takes over, its predecessor's copies go back
        let sent = [chunk(20, 0), first[2], chunk(20, 1), chunk(10, 9)];
        assert_eq!(take(&mut rx, &sent), vec![(20, 0), (20, 1)]);
        let by = crate::wire::named_reasons(&rx.rejected_by_reason());
        assert_eq!(by, [("out_of_order", 4)].into_iter().collect());
        // a restarted replay: an old copy comes first, and the real stream still goes on
        let mut fresh = TrajectoryReceiver::new(&t, OBS, ACT, 100).unwrap();
        drop(rx);
        let sent = [first[1], chunk(20, 100_000), chunk(20, 100_001)];
        assert_eq!(
            take(&mut fresh, &sent),
            vec![(10, 1), (20, 100_000), (20, 100_001)]
        );
        assert_eq!(fresh.rejected(), 0);
    }

    /// Both ends of the batch services and an injector on a run of the test's own prefix `name`,
    /// the prefix first: bound in this order, it is dropped (and cleaned up) last.
    fn batch_ends(name: &str) -> (Isolated, RunTransport, BatchServer, ReplayClient, Injector) {
        let isolated = Isolated::new(name);
        let t = RunTransport::open(&isolated.0, 1, "test", &crate::test_key()).unwrap();
        let server = BatchServer::new(&t, OBS, ACT, 1 << 12).unwrap();
        let client = ReplayClient::new(&t, OBS, ACT, Duration::from_secs(5)).unwrap();
        let inject = Injector::new(&t).unwrap();
        (isolated, t, server, client, inject)
    }

    #[test]
    fn batches_rewritten_in_shared_memory_are_returned_as_validated_or_rejected() {
        let (_isolated, _t, mut server, mut client, inject) = batch_ends("inject-batches");
        let (batch, length) = (2, 3);
        let spec = BatchSpec::Sequence { batch, length };
        let n = batch * length;
        let sent = SequenceBatch {
            batch,
            length,
            obs_dim: OBS,
            act_dim: ACT,
            obs: (0..n * OBS).map(|i| i as f32).collect(),
            action: vec![0.5; n * ACT],
            reward: vec![1.0; n],
            is_first: vec![0.0; n],
            is_terminal: vec![0.0; n],
            context: vec![0.25; n * 2],
            mask: vec![0.0; n * 2],
            has_mask: vec![0.0; n],
        };
        let payload = sent.arrays().concat();
        let reward = n * (OBS + ACT);
        let wait = Duration::from_millis(200);
        for when in WHEN {
            // the client asks (again, after a rejection), and the answer carries the request's
            // id
            assert_eq!(client.next_batch(spec, Duration::ZERO).unwrap(), None);
            let (request, _) = server.receive_requests().unwrap().pop().expect("a request");
            let header = BatchHeader {
                kind: BatchKind::Sequence.code(),
                batch: batch as u32,
                length: length as u32,
                frames: 1,
                obs_dim: OBS as u32,
                act_dim: ACT as u32,
                ..BatchHeader::answering(&request)
            }
            .sealed(&crate::test_key(), &[&payload]);
            let held = inject.batch_held(header, &payload).unwrap();
            assert_eq!(held.reached, 1);
            let rewrite = || {
                held.set_header(BatchHeader {
                    batch: 999,
                    obs_dim: 200,
                    ..header
                });
                held.set(reward, f32::NAN).unwrap();
            };
            if when == When::BeforeRead {
                held.set(reward, f32::NAN).unwrap();
            }
            let mut hook = rewrite_at(when, rewrite);
            let got = client.next_batch_observed(spec, wait, &mut hook).unwrap();
            if when == When::BeforeRead {
                assert_eq!(got, None);
                assert_eq!(client.rejected(), 1);
            } else {
                assert_eq!(got, Some(Batch::Sequence(sent.clone())), "{when:?}");
            }
        }
        assert_eq!(client.rejected(), 1);
    }

    /// A request the replay cannot read is answered with a refusal naming why; the learner
    /// counts it by that reason and asks again only after [`crate::RESEND_AFTER`].
    #[test]
    fn a_refused_request_reaches_the_learner_with_its_reason() {
        let (_isolated, _t, mut server, mut client, inject) = batch_ends("inject-refusal");
        let spec = BatchSpec::Sequence {
            batch: 2,
            length: 3,
        };
        assert_eq!(client.next_batch(spec, Duration::ZERO).unwrap(), None);
        let (request, _) = server.receive_requests().unwrap().pop().expect("a request");
        // a request rewritten by a process without the run's key (its CRC-32 right) is
        // rejected without an answer: nothing in it, its id included, can be trusted
        let forged = BatchRequest {
            batch: 4,
            ..request
        }
        .seal_with(&forger(), &[]);
        inject.request(forged).unwrap();
        assert!(server.receive_requests().unwrap().is_empty());
        // the request as a faulty learner sends it: an unknown kind
        let unknown = BatchRequest { kind: 7, ..request }.seal_with(&crate::test_key(), &[]);
        inject.request(unknown).unwrap();
        assert!(server.receive_requests().unwrap().is_empty());
        let rejected = crate::wire::named_reasons(&server.rejected_by_reason());
        let want = [("kind", 1), ("unauthenticated", 1)];
        assert_eq!(rejected, want.into_iter().collect());
        let wait = Duration::from_millis(300);
        assert_eq!(client.next_batch(spec, wait).unwrap(), None);
        let refused = crate::wire::named_reasons(&client.refused_by_reason());
        assert_eq!(refused, [("kind", 1)].into_iter().collect());
        // no new request within RESEND_AFTER of the refusal, one after it
        assert!(server.receive_requests().unwrap().is_empty());
        std::thread::sleep(crate::RESEND_AFTER);
        assert_eq!(client.next_batch(spec, Duration::ZERO).unwrap(), None);
        let again = server.receive_requests().unwrap();
        assert_eq!(again.len(), 1);
        assert!(again[0].0.request_id > request.request_id);
    }

    #[test]
    fn weights_rewritten_in_shared_memory_are_loaded_as_verified_or_rejected() {
        let isolated = Isolated::new("inject-weights");
        let t = RunTransport::open(&isolated.0, 1, "test", &crate::test_key()).unwrap();
        let mut rx = WeightsReceiver::new(&t, 10).unwrap();
        let inject = Injector::new(&t).unwrap();
        let bytes: Vec<u8> = (0..1000).map(|i| i as u8).collect();
        for (version, when) in WHEN.into_iter().enumerate() {
            let header = WeightsHeader::new(version as u64 + 1, bytes.len())
                .seal_with(&crate::test_key(), &[&bytes]);
            let held = inject.weights_held(header, &bytes).unwrap();
            assert_eq!(held.reached, 1);
            let rewrite = || {
                held.set(7, 0xff).unwrap();
                held.set_header(WeightsHeader { len: 1, ..header });
            };
            if when == When::BeforeRead {
                held.set(7, 0xff).unwrap();
            }
            let mut hook = rewrite_at(when, rewrite);
            let got = rx
                .latest_with_observed(&mut hook, |v, b| (v, b.to_vec()))
                .unwrap();
            if when == When::BeforeRead {
                assert_eq!(got, None);
                assert_eq!(rx.rejected(), 1);
            } else {
                assert_eq!(got, Some((header.version, bytes.clone())), "{when:?}");
            }
        }
        assert_eq!(rx.rejected(), 1);
    }

    /// Issue 47's second poisoned value: weights whose header version is rewritten to 2^64-1
    /// in shared memory fail the checksum; sent sealed with the run's key (a faulty learner),
    /// the version is beyond the run's gradient steps; and the probe that locked both actors
    /// onto a plausible version, the header rewritten with its CRC-32 computed again, fails its
    /// tag. The actor keeps loading the learner's newer weights.
    #[test]
    fn an_absurd_or_forged_weights_version_is_rejected_and_newer_weights_still_load() {
        let isolated = Isolated::new("inject-version");
        let t = RunTransport::open(&isolated.0, 1, "test", &crate::test_key()).unwrap();
        let mut rx = WeightsReceiver::new(&t, 10).unwrap();
        let inject = Injector::new(&t).unwrap();
        let bytes = vec![5u8; 100];
        let header = |key: &RunKey, version| {
            WeightsHeader::new(version, bytes.len()).seal_with(key, &[&bytes])
        };
        let key = crate::test_key();
        let held = inject.weights_held(header(&key, 1), &bytes).unwrap();
        held.set_header(WeightsHeader {
            version: u64::MAX,
            ..header(&key, 1)
        });
        assert_eq!(rx.latest_with(|v, _| v).unwrap(), None);
        assert_eq!(rx.rejected(), 1);
        assert_eq!(inject.weights(header(&key, u64::MAX), &bytes).unwrap(), 1);
        assert_eq!(rx.latest_with(|v, _| v).unwrap(), None);
        assert_eq!(inject.weights(header(&forger(), 9), &bytes).unwrap(), 1);
        assert_eq!(rx.latest_with(|v, _| v).unwrap(), None);
        let by = crate::wire::named_reasons(&rx.rejected_by_reason());
        let want = [("checksum", 1), ("implausible", 1), ("unauthenticated", 1)];
        assert_eq!(by, want.into_iter().collect());
        for version in 2..4 {
            assert_eq!(inject.weights(header(&key, version), &bytes).unwrap(), 1);
            assert_eq!(rx.latest_with(|v, _| v).unwrap(), Some(version));
        }
    }

    /// An answer forged for the learner's outstanding request (its id and epoch, read in shared
    /// memory, with a valid CRC-32) is rejected as unauthenticated, and the request stays
    /// outstanding: it is sent again under the same id, and the replay's real answer is taken.
    /// An answer to another client's request (a restarted learner's predecessor) is ignored.
    #[test]
    fn a_forged_answer_neither_feeds_the_learner_nor_cancels_its_request() {
        let (_isolated, _t, mut server, mut client, inject) = batch_ends("inject-forged-answer");
        let (batch, length) = (1, 2);
        let spec = BatchSpec::Sequence { batch, length };
        let n = batch * length;
        let sent = SequenceBatch {
            batch,
            length,
            obs_dim: OBS,
            act_dim: ACT,
            obs: vec![0.5; n * OBS],
            action: vec![0.5; n * ACT],
            reward: vec![1.0; n],
            is_first: vec![0.0; n],
            is_terminal: vec![0.0; n],
            context: vec![0.25; n * 2],
            mask: vec![0.0; n * 2],
            has_mask: vec![0.0; n],
        };
        assert_eq!(client.next_batch(spec, Duration::ZERO).unwrap(), None);
        let (request, _) = server.receive_requests().unwrap().pop().expect("a request");
        let payload = sent.arrays().concat();
        let answer = BatchHeader {
            kind: BatchKind::Sequence.code(),
            batch: batch as u32,
            length: length as u32,
            frames: 1,
            obs_dim: OBS as u32,
            act_dim: ACT as u32,
            ..BatchHeader::answering(&request)
        };
        let forged: Vec<f32> = payload.iter().map(|v| v + 1.0).collect();
        inject
            .batch_held(answer.sealed(&forger(), &[&forged]), &forged)
            .unwrap();
        let other_client = BatchHeader {
            client: request.client + 1,
            ..answer
        };
        inject
            .batch_held(other_client.sealed(&crate::test_key(), &[&forged]), &forged)
            .unwrap();
        let wait = Duration::from_millis(200);
        assert_eq!(client.next_batch(spec, wait).unwrap(), None);
        let rejected = crate::wire::named_reasons(&client.rejected_by_reason());
        assert_eq!(rejected, [("unauthenticated", 1)].into_iter().collect());
        // asked again at once, under the same id
        let again = server.receive_requests().unwrap();
        assert_eq!(again.len(), 1);
        assert_eq!(again[0].0, request);
        server.send_sequence(&request, &sent).unwrap();
        let got = client.next_batch(spec, Duration::from_secs(5)).unwrap();
        assert_eq!(got, Some(Batch::Sequence(sent)));
    }
}
