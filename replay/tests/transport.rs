//! Actors, replay and learner on threads of one process over a private iceoryx2 prefix.

use ctxrace_config::{Batch, BatchSpec, ReplayOptions};
use ctxrace_ipc::{
    cleanup, Isolated, ReplayBeacon, ReplayClient, RunKey, RunTransport, SenderOptions,
    TrajectoryReceiver, TrajectorySender, TrajectoryStep, TRAJECTORY_BUFFER,
};
use ctxrace_replay::{read_snapshot, run, ReplayArgs, ReplayBuffer, ReplayControl, SnapshotShape};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::thread;
use std::time::{Duration, Instant};

/// The key of the tests' runs.
fn key() -> RunKey {
    RunKey::from_bytes([5; ctxrace_ipc::KEY_LEN])
}

const OBS: usize = 3;
const ACT: usize = 2;
const STEPS: usize = 1000;
const EPISODE: usize = 100;

fn actor(prefix: String, id: u32, poison: bool) -> ctxrace_ipc::SenderStats {
    let t = RunTransport::open(&prefix, 2, &format!("actor{id}"), &key()).unwrap();
    let opts = SenderOptions {
        handshake_timeout: Duration::from_secs(30),
        close_timeout: Duration::from_secs(5),
    };
    let mut tx = TrajectorySender::new(&t, id, OBS, ACT, opts).unwrap();
    for k in 0..STEPS {
        let e = k % EPISODE;
        let obs = [id as f32, k as f32, 0.5];
        let action = if e == 0 { [0.0; 2] } else { [0.1, -0.1] };
        let step = TrajectoryStep {
            obs: &obs,
            action: &action,
            reward: 1.0,
            is_first: e == 0,
            is_terminal: e == EPISODE - 1 && (k / EPISODE).is_multiple_of(2),
            is_last: e == EPISODE - 1,
            context: [0.2, -0.3],
            mask: (e != 0).then_some([0.25, 1.0]),
        };
        tx.push((k / EPISODE) as u64, 0, &step).unwrap();
    }
    if poison {
        // A NaN observation in an episode of its own: the replay must reject that chunk only.
        let step = TrajectoryStep {
            obs: &[f32::NAN, 0.0, 0.0],
            action: &[0.0, 0.0],
            reward: 0.0,
            is_first: true,
            is_terminal: false,
            is_last: true,
            context: [0.0, 0.0],
            mask: None,
        };
        tx.push(99, 0, &step).unwrap();
    }
    // A step of the wrong size is refused locally, without sending anything.
    let bad = TrajectoryStep {
        obs: &[0.0],
        action: &[0.0, 0.0],
        reward: 0.0,
        is_first: true,
        is_terminal: false,
        is_last: true,
        context: [0.0, 0.0],
        mask: None,
    };
    assert!(tx.push(100, 0, &bad).is_err());
    // what the replay's queue cannot hold waits in the backlog until the replay takes it
    tx.close().unwrap()
}

/// The replay of one actor: 0.5 sampled steps per inserted step after 200 inserts, 100 inserts
/// of slack either way, a budget of `env_steps`.
fn one_actor_at_half_a_sample_per_insert(
    prefix: &str,
    env_steps: u64,
    streams_path: Option<std::path::PathBuf>,
) -> ReplayArgs {
    ReplayArgs {
        prefix: prefix.to_string(),
        actors: 1,
        obs_dim: OBS,
        act_dim: ACT,
        options: ReplayOptions {
            capacity: 10_000,
            min_fill: 200,
            samples_per_insert: 0.5,
            error_buffer_steps: 100.0,
            snapshot_every_secs: 0,
            ..Default::default()
        },
        max_policy_version: 0,
        env_steps,
        sampled_at_least: 0,
        handle_signals: false,
        streams_path,
    }
}

/// Pushes the steps `steps` of episodes of 100, step `k` observing `[0, k, 0]`.
fn push_episodes(tx: &mut TrajectorySender, steps: std::ops::Range<u64>) {
    for k in steps {
        let step = TrajectoryStep {
            obs: &[0.0, k as f32, 0.0],
            action: &[0.0, 0.0],
            reward: 0.0,
            is_first: k.is_multiple_of(100),
            is_terminal: false,
            is_last: k % 100 == 99,
            context: [0.0, 0.0],
            mask: None,
        };
        tx.push(k / 100, 0, &step).unwrap();
    }
}

#[test]
fn two_actors_fill_the_replay_and_the_learner_gets_batches() {
    let isolated = Isolated::new("transport");
    let prefix = isolated.0.clone();
    let dir = tempfile::tempdir().unwrap();
    let snap = dir.path().join("replay.snap");
    let args = ReplayArgs {
        prefix: prefix.clone(),
        actors: 2,
        obs_dim: OBS,
        act_dim: ACT,
        options: ReplayOptions {
            capacity: 10_000,
            min_fill: 2 * STEPS,
            samples_per_insert: 0.0,
            snapshot_every_secs: 0,
            snapshot_path: Some(snap.clone()),
            ..Default::default()
        },
        max_policy_version: 0,
        env_steps: u64::MAX,
        sampled_at_least: 0,
        handle_signals: false,
        streams_path: None,
    };
    // Actors start first: their handshake must wait for the replay.
    let actors: Vec<_> = (0..2)
        .map(|id| {
            let p = prefix.clone();
            thread::spawn(move || actor(p, id, id == 1))
        })
        .collect();
    thread::sleep(Duration::from_millis(300));
    let control = Arc::new(ReplayControl::default());
    let replay = {
        let c = control.clone();
        let a = args.clone();
        thread::spawn(move || run(&a, &key(), &c))
    };
    let stats: Vec<_> = actors.into_iter().map(|h| h.join().unwrap()).collect();
    assert_eq!(stats[0].sent_steps, STEPS as u64);
    assert_eq!(stats[1].sent_steps, STEPS as u64 + 1);
    assert_eq!(stats[0].dropped_steps + stats[1].dropped_steps, 0);

    let t = RunTransport::open(&prefix, 2, "learner", &key()).unwrap();
    let mut client = ReplayClient::new(&t, OBS, ACT, Duration::from_secs(10)).unwrap();
    let spec = BatchSpec::Sequence {
        batch: 4,
        length: 10,
    };
    let Some(Batch::Sequence(s)) = client.next_batch(spec, Duration::from_secs(10)).unwrap() else {
        panic!("no sequence batch");
    };
    assert_eq!((s.batch, s.length, s.obs_dim, s.act_dim), (4, 10, OBS, ACT));
    assert_eq!(s.obs.len(), 4 * 10 * OBS);
    for seq in s.obs.chunks(10 * OBS) {
        let actor = seq[0];
        let k: Vec<f32> = seq.chunks(OBS).map(|f| f[1]).collect();
        assert!(seq.chunks(OBS).all(|f| f[0] == actor));
        assert!(k.windows(2).all(|w| w[1] == w[0] + 1.0), "{k:?}");
    }
    for (i, first) in s.is_first.iter().enumerate() {
        let k = s.obs[i * OBS + 1] as usize;
        assert_eq!(*first == 1.0, k.is_multiple_of(EPISODE));
        // the acting masks arrive with their steps
        assert_eq!(s.has_mask[i], 1.0 - first);
        let want = if *first == 1.0 {
            [0.0, 0.0]
        } else {
            [0.25, 1.0]
        };
        assert_eq!(s.mask[2 * i..2 * i + 2], want);
    }
    // the paper's code's pairing travels with the request: the reward and terminal flag of the
    // step after next, so no transition starts at an episode's last two steps
    let spec = BatchSpec::Transition {
        batch: 8,
        frames: 2,
        reward_delay: 1,
    };
    let Some(Batch::Transition(tr)) = client.next_batch(spec, Duration::from_secs(10)).unwrap()
    else {
        panic!("no transition batch");
    };
    assert_eq!((tr.batch, tr.obs_dim, tr.act_dim), (8, 2 * OBS, ACT));
    for (i, terminal) in tr.terminal.iter().enumerate() {
        let k = tr.obs[i * 2 * OBS + OBS + 1] as usize;
        assert!(k % EPISODE < EPISODE - 2, "a transition from step {k}");
        let late = k + 2;
        let ends = late % EPISODE == EPISODE - 1 && (late / EPISODE).is_multiple_of(2);
        assert_eq!(*terminal == 1.0, ends, "step {k}");
    }
    assert_eq!(client.rejected(), 0);

    let start = Instant::now();
    while control.inserted.load(Ordering::Acquire) < 2 * STEPS as u64 {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "replay did not take every step"
        );
        thread::sleep(Duration::from_millis(10));
    }
    control.shutdown.store(true, Ordering::Release);
    let status = replay.join().unwrap().unwrap();
    assert_eq!(status.inserted, 2 * STEPS as u64);
    assert_eq!(status.fill, 2 * STEPS as u64);
    assert_eq!(status.rejected, 1);
    assert_eq!(status.dropped_chunks, 0);
    assert_eq!(status.batches, 2);
    assert_eq!(status.sampled, 4 * 10 + 8);

    let shape = SnapshotShape::of(&ReplayBuffer::new(10_000, 2, OBS, ACT));
    let (restored, counts) = read_snapshot(&snap, shape).unwrap();
    assert_eq!(restored.len(), 2 * STEPS);
    assert_eq!(counts.samples, 48);

    drop(client);
    drop(t);
    let report = cleanup(&prefix).unwrap();
    assert_eq!(report.alive_nodes, 0, "{report:?}");
    assert!(!std::fs::read_dir("/dev/shm")
        .unwrap()
        .flatten()
        .any(|e| e.file_name().to_string_lossy().starts_with(&prefix)));
}

#[test]
fn a_stuck_replay_does_not_freeze_the_actor() {
    let isolated = Isolated::new("stuck");
    let prefix = isolated.0.clone();
    {
        let t = RunTransport::open(&prefix, 1, "replay", &key()).unwrap();
        // A replay that comes up and then never reads.
        let _stuck = TrajectoryReceiver::new(&t, OBS, ACT, 0).unwrap();
        ReplayBeacon::new(&t).unwrap().signal();
        let a = RunTransport::open(&prefix, 1, "actor0", &key()).unwrap();
        let opts = SenderOptions {
            handshake_timeout: Duration::from_secs(5),
            close_timeout: Duration::from_millis(50),
        };
        let mut tx = TrajectorySender::new(&a, 0, OBS, ACT, opts).unwrap();
        let start = Instant::now();
        let chunks = TRAJECTORY_BUFFER + 20;
        for k in 0..chunks {
            let step = TrajectoryStep {
                obs: &[0.0, k as f32, 0.0],
                action: &[0.0, 0.0],
                reward: 0.0,
                is_first: true,
                is_terminal: false,
                is_last: true,
                context: [0.0, 0.0],
                mask: None,
            };
            tx.push(k as u64, 0, &step).unwrap();
        }
        let stats = tx.close().unwrap();
        // A chunk finding the queue full costs one short attempt and waits in the backlog;
        // closing gives the replay the close timeout, then drops and counts what is left.
        assert!(
            start.elapsed() < Duration::from_secs(2),
            "{:?}",
            start.elapsed()
        );
        assert_eq!(stats.sent_chunks + stats.dropped_chunks, chunks as u64);
        assert_eq!(stats.sent_chunks, TRAJECTORY_BUFFER as u64);
        assert_eq!(stats.dropped_steps, 20);
    }
    let report = cleanup(&prefix).unwrap();
    assert_eq!(report.alive_nodes, 0);
}

/// A replay at half a sample per insert, unbounded, on a thread of its own prefix (`name`), and
/// an actor's sender that has pushed it 600 steps.
fn limited_replay(
    name: &str,
) -> (
    Isolated,
    Arc<ReplayControl>,
    thread::JoinHandle<Result<ctxrace_ipc::ReplayStatus, ctxrace_replay::ReplayError>>,
    RunTransport,
    TrajectorySender,
) {
    let isolated = Isolated::new(name);
    let args = one_actor_at_half_a_sample_per_insert(&isolated.0, u64::MAX, None);
    let control = Arc::new(ReplayControl::default());
    let replay = {
        let c = control.clone();
        thread::spawn(move || run(&args, &key(), &c))
    };
    let t = RunTransport::open(&isolated.0, 1, "actor0", &key()).unwrap();
    let mut tx = TrajectorySender::new(&t, 0, OBS, ACT, SenderOptions::default()).unwrap();
    push_episodes(&mut tx, 0..600);
    (isolated, control, replay, t, tx)
}

#[test]
fn the_rate_limiter_holds_the_samples_per_insert_ratio() {
    let (_isolated, control, replay, t, tx) = limited_replay("ratio");
    let mut client = ReplayClient::new(&t, OBS, ACT, Duration::from_secs(10)).unwrap();
    // the ratio's window is 2 · 0.5 · 100 = 100 samples: a request for 101 can never be
    // served; it is rejected and counted instead of blocking the queue
    let too_big = BatchSpec::Transition {
        batch: 101,
        frames: 1,
        reward_delay: 0,
    };
    assert!(client
        .next_batch(too_big, Duration::from_millis(500))
        .unwrap()
        .is_none());
    // the replay's reason reached the learner
    let refused = ctxrace_ipc::wire::named_reasons(&client.refused_by_reason());
    assert_eq!(refused, [("unservable", 1)].into_iter().collect());
    let spec = BatchSpec::Transition {
        batch: 50,
        frames: 1,
        reward_delay: 0,
    };
    let mut batches = 0;
    while client
        .next_batch(spec, Duration::from_millis(500))
        .unwrap()
        .is_some()
    {
        batches += 1;
        assert!(batches < 100, "the limiter let too much through");
    }
    // the limiter holds the last request: the client sends it again after RESEND_AFTER, and
    // the replay does not queue it twice
    let waited = ctxrace_ipc::RESEND_AFTER + Duration::from_millis(500);
    assert!(client.next_batch(spec, waited).unwrap().is_none());
    assert_eq!(client.resent(), 1);
    // the replay drains its senders when stopping: close ours first
    drop(tx);
    control.shutdown.store(true, Ordering::Release);
    let status = replay.join().unwrap().unwrap();
    // 600 inserts allow 0.5·600 samples less the slack of 0.5·100: 250 samples = 5 batches.
    assert_eq!(status.inserted, 600);
    assert_eq!(batches, 5);
    assert_eq!(status.sampled, 250);
    assert_eq!(status.pending_requests, 1);
    assert_eq!(status.rejected, 1);
}

/// A request held past the renewal time goes out again from a new publisher, the old one
/// dropped (a damaged publisher's requests may never be readable): the replay takes the copy as
/// the duplicate it is, serves the held request once inserts allow it, and serves the next
/// request, which only the new publisher can have sent.
#[test]
fn a_request_unanswered_for_long_is_sent_again_from_a_new_publisher() {
    let (_isolated, control, replay, t, mut tx) = limited_replay("renew");
    let resend = ctxrace_ipc::RESEND_AFTER;
    let mut client = ReplayClient::new(&t, OBS, ACT, Duration::from_secs(10))
        .unwrap()
        .with_renew_after(resend);
    let spec = BatchSpec::Transition {
        batch: 50,
        frames: 1,
        reward_delay: 0,
    };
    let wait = Duration::from_millis(500);
    let mut batches = 0;
    while client.next_batch(spec, wait).unwrap().is_some() {
        batches += 1;
        assert!(batches < 100, "the limiter let too much through");
    }
    // held by the limiter: sent again twice, each time from a new publisher
    assert!(client
        .next_batch(spec, 2 * resend + wait)
        .unwrap()
        .is_none());
    assert_eq!((client.resent(), client.publishers_renewed()), (2, 2));
    // inserts for two more batches: the held request's and the next one's
    push_episodes(&mut tx, 600..800);
    for _ in 0..2 {
        let batch = client.next_batch(spec, Duration::from_secs(10)).unwrap();
        assert!(batch.is_some(), "no answer after the publisher was renewed");
        batches += 1;
    }
    drop(tx);
    control.shutdown.store(true, Ordering::Release);
    let status = replay.join().unwrap().unwrap();
    // every batch served once: 800 inserts allow 0.5·800 - 50 = 350 samples, 7 batches
    assert_eq!((status.inserted, status.sampled, batches), (800, 350, 7));
    assert_eq!((status.pending_requests, status.rejected), (0, 0));
}

/// The replay stores the run's env-step budget and no more: the steps past it wait at the actor
/// until the replay stops, which takes them and counts them as surplus, by actor; meanwhile the
/// learner takes its batches without waiting for inserts.
#[test]
fn the_replay_stores_the_budget_counts_the_surplus_and_lets_the_learner_finish() {
    let isolated = Isolated::new("budget");
    let prefix = isolated.0.clone();
    let dir = tempfile::tempdir().unwrap();
    let streams_path = dir.path().join("replay-streams.json");
    // not a chunk boundary: the chunk across it is stored in part
    let args = one_actor_at_half_a_sample_per_insert(&prefix, 437, Some(streams_path.clone()));
    let control = Arc::new(ReplayControl::default());
    let replay = {
        let (a, c) = (args.clone(), control.clone());
        thread::spawn(move || run(&a, &key(), &c))
    };
    let t = RunTransport::open(&prefix, 1, "actor0", &key()).unwrap();
    let mut tx = TrajectorySender::new(&t, 0, OBS, ACT, SenderOptions::default()).unwrap();
    // more than the replay's queue holds: the rest waits in the actor's backlog
    push_episodes(&mut tx, 0..2000);
    let mut client = ReplayClient::new(&t, OBS, ACT, Duration::from_secs(10)).unwrap();
    let spec = BatchSpec::Transition {
        batch: 50,
        frames: 1,
        reward_delay: 0,
    };
    // the ratio alone would allow 0.5·437 − 0.5·100 samples, 3 batches: once the budget is
    // stored no insert will come, so the learner is not held to it
    for _ in 0..8 {
        let batch = client.next_batch(spec, Duration::from_secs(10)).unwrap();
        let Some(Batch::Transition(b)) = batch else {
            panic!("no batch after the budget was stored");
        };
        // nothing past the budget was stored
        assert!(b.obs.chunks(OBS).all(|f| f[1] < 437.0), "{:?}", b.obs);
    }
    // the replay took nothing more while it ran: the actor's steps past the budget wait in its
    // queue and backlog
    let held = tx.stats();
    assert!(held.sent_steps < 2000 && tx.backlog() > 0, "{held:?}");
    // stopping, the replay takes all of them (not stored) while the actor closes
    control.shutdown.store(true, Ordering::Release);
    assert_eq!(tx.close().unwrap().sent_steps, 2000);
    let status = replay.join().unwrap().unwrap();
    assert_eq!((status.inserted, status.fill), (437, 437));
    assert_eq!(status.sampled, 8 * 50);
    let streams: ctxrace_run::results::ReplayStreams =
        ctxrace_run::results::read_json(&streams_path).unwrap();
    assert!(streams.budget_stored(), "{streams:?}");
    assert_eq!(
        (streams.stored_by_actor, streams.surplus_by_actor),
        (vec![437], vec![1563])
    );
}

#[test]
fn a_chunk_rewritten_after_validation_cannot_panic_the_replay_buffer() {
    use ctxrace_ipc::wire::{step_stride, ChunkHeader};
    use ctxrace_ipc::ReadStage;
    use ctxrace_ipc_inject::Injector;
    use ctxrace_replay::ReplayBuffer;
    use rand::SeedableRng;
    let isolated = Isolated::new("rewritten");
    let t = RunTransport::open(&isolated.0, 2, "replay", &key()).unwrap();
    let mut rx = TrajectoryReceiver::new(&t, OBS, ACT, 0).unwrap();
    let inject = Injector::new(&t).unwrap();
    let mut buffer = ReplayBuffer::new(100, 2, OBS, ACT);
    let stride = step_stride(OBS, ACT);
    let steps = 4;
    let payload: Vec<f32> = (0..steps * stride)
        .map(|i| match i % stride {
            o if o < OBS => i as f32,
            r if r == OBS + ACT => 1.0,
            _ => 0.0,
        })
        .collect();
    for (sequence, stage) in [ReadStage::Copied, ReadStage::Validated]
        .into_iter()
        .enumerate()
    {
        let header = ChunkHeader {
            sequence: sequence as u64,
            steps: steps as u32,
            ..ChunkHeader::for_actor(0, OBS, ACT)
        }
        .sealed(&key(), &payload);
        let held = inject.chunk_held(0, header, &payload).unwrap();
        // an actor id past the buffer's streams, dimensions and a step count past the payload,
        // and a NaN reward, written into shared memory once the reader has copied or
        // validated the chunk
        let mut hook = |at: ReadStage| {
            if at == stage {
                held.set_header(ChunkHeader {
                    actor_id: 9,
                    obs_dim: 1000,
                    act_dim: 7,
                    steps: 64,
                    ..header
                });
                held.set(OBS + ACT, f32::NAN).unwrap();
            }
        };
        // what the replay's loop does with each chunk
        let taken = rx
            .receive_observed(1, &mut hook, |c| {
                buffer.insert_chunk(c.header.actor_id as usize, c.payload, c.after_gap)
            })
            .unwrap();
        assert_eq!(taken, 1);
    }
    assert_eq!(rx.rejected(), 0);
    // both chunks stored as sent, in actor 0's stream
    assert_eq!(buffer.len(), 2 * steps);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let batch = buffer.sample_sequences(1, 2 * steps, &mut rng).unwrap();
    let obs: Vec<f32> = payload
        .chunks(stride)
        .flat_map(|step| step[..OBS].to_vec())
        .collect();
    assert_eq!(batch.obs, [obs.clone(), obs].concat());
    assert_eq!(batch.reward, vec![1.0; 2 * steps]);
}
