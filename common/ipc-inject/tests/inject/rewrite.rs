//! Messages rewritten in shared memory while a receiver holds them, forged without the run's
//! key, or flooding a service: each is stored as validated or rejected by its reason, and the
//! genuine messages around it are taken.

use ctxrace_ipc::{BatchHeader, BatchRequest, ChunkHeader, RunTransport, WeightsHeader};
use ctxrace_ipc_inject::Injector;

use crate::test_key;
use ctxrace_config::batch::{Batch, BatchSpec, SequenceBatch};
use ctxrace_ipc::wire::{step_stride, BatchKind, Sealed as _};
use ctxrace_ipc::RunKey;
use ctxrace_ipc::{
    BatchServer, Isolated, ReadStage, ReplayClient, TrajectoryReceiver, WeightsReceiver,
};
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
    let t = RunTransport::open(&isolated.0, 2, "replay", &test_key()).unwrap();
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
        .sealed(&test_key(), &payload);
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
    RunKey::from_bytes([3; ctxrace_ipc::KEY_LEN])
}

/// Issue 47's first poisoned value: a chunk whose sequence is rewritten to 2^63 in shared
/// memory fails its checksum; written with a matching checksum by a process without the
/// run's key it fails its tag; either way the actor's stream goes on from where it was. A
/// chunk (sealed with the run's key, as by a faulty actor) naming weights beyond the run's
/// target, an episode going back or jumping ahead of its sequence is rejected too.
#[test]
fn a_rewritten_or_forged_chunk_is_rejected_and_does_not_stop_the_stream() {
    let isolated = Isolated::new("inject-sequence");
    let t = RunTransport::open(&isolated.0, 1, "replay", &test_key()).unwrap();
    let mut rx = TrajectoryReceiver::new(&t, OBS, ACT, 10).unwrap();
    let inject = Injector::new(&t).unwrap();
    let (key, forger) = (test_key(), forger());
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
    let by = ctxrace_ipc::wire::named_reasons(&rx.rejected_by_reason());
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
    let t = RunTransport::open(&isolated.0, 1, "replay", &test_key()).unwrap();
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
            .chunk(0, chunk(&test_key(), 7, sequence), &payload)
            .unwrap();
        rx.receive(8, |c| stored.push(c.header.sequence)).unwrap();
    }
    assert_eq!(stored, (0..12).collect::<Vec<_>>());
    let by = ctxrace_ipc::wire::named_reasons(&rx.rejected_by_reason());
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
    let key = test_key();
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
    let by = ctxrace_ipc::wire::named_reasons(&rx.rejected_by_reason());
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
    let t = RunTransport::open(&isolated.0, 1, "test", &test_key()).unwrap();
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
        .sealed(&test_key(), &[&payload]);
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
/// counts it by that reason and asks again only after [`ctxrace_ipc::RESEND_AFTER`].
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
    let unknown = BatchRequest { kind: 7, ..request }.seal_with(&test_key(), &[]);
    inject.request(unknown).unwrap();
    assert!(server.receive_requests().unwrap().is_empty());
    let rejected = ctxrace_ipc::wire::named_reasons(&server.rejected_by_reason());
    let want = [("kind", 1), ("unauthenticated", 1)];
    assert_eq!(rejected, want.into_iter().collect());
    let wait = Duration::from_millis(300);
    assert_eq!(client.next_batch(spec, wait).unwrap(), None);
    let refused = ctxrace_ipc::wire::named_reasons(&client.refused_by_reason());
    assert_eq!(refused, [("kind", 1)].into_iter().collect());
    // no new request within RESEND_AFTER of the refusal, one after it
    assert!(server.receive_requests().unwrap().is_empty());
    std::thread::sleep(ctxrace_ipc::RESEND_AFTER);
    assert_eq!(client.next_batch(spec, Duration::ZERO).unwrap(), None);
    let again = server.receive_requests().unwrap();
    assert_eq!(again.len(), 1);
    assert!(again[0].0.request_id > request.request_id);
}

#[test]
fn weights_rewritten_in_shared_memory_are_loaded_as_verified_or_rejected() {
    let isolated = Isolated::new("inject-weights");
    let t = RunTransport::open(&isolated.0, 1, "test", &test_key()).unwrap();
    let mut rx = WeightsReceiver::new(&t, 10).unwrap();
    let inject = Injector::new(&t).unwrap();
    let bytes: Vec<u8> = (0..1000).map(|i| i as u8).collect();
    for (version, when) in WHEN.into_iter().enumerate() {
        let header =
            WeightsHeader::new(version as u64 + 1, bytes.len()).seal_with(&test_key(), &[&bytes]);
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
    let t = RunTransport::open(&isolated.0, 1, "test", &test_key()).unwrap();
    let mut rx = WeightsReceiver::new(&t, 10).unwrap();
    let inject = Injector::new(&t).unwrap();
    let bytes = vec![5u8; 100];
    let header =
        |key: &RunKey, version| WeightsHeader::new(version, bytes.len()).seal_with(key, &[&bytes]);
    let key = test_key();
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
    let by = ctxrace_ipc::wire::named_reasons(&rx.rejected_by_reason());
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
        .batch_held(other_client.sealed(&test_key(), &[&forged]), &forged)
        .unwrap();
    let wait = Duration::from_millis(200);
    assert_eq!(client.next_batch(spec, wait).unwrap(), None);
    let rejected = ctxrace_ipc::wire::named_reasons(&client.rejected_by_reason());
    assert_eq!(rejected, [("unauthenticated", 1)].into_iter().collect());
    // asked again at once, under the same id
    let again = server.receive_requests().unwrap();
    assert_eq!(again.len(), 1);
    assert_eq!(again[0].0, request);
    server.send_sequence(&request, &sent).unwrap();
    let got = client.next_batch(spec, Duration::from_secs(5)).unwrap();
    assert_eq!(got, Some(Batch::Sequence(sent)));
}
