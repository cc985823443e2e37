//! `ctxrace bench ipc`: the transport's throughput and latencies, with the same transfers over
//! Unix domain sockets and bincode as the baseline.
//!
//! Three measurements, each over iceoryx2 and then over sockets, all on threads of this process:
//! env steps per second from N actors into the replay buffer (synthetic steps, no simulator),
//! the latency from a learner's batch request to the decoded batch, and the latency of a weights
//! broadcast to M subscribers (until the last one holds verified weights).

use anyhow::{anyhow, Context as _, Result};
use ctxrace_config::{Batch, BatchSpec, ReplayOptions, SequenceBatch};
use ctxrace_ipc::wire::{step_stride, MAX_CHUNK};
use ctxrace_ipc::{
    cleanup, run_prefix, ReplayClient, RunKey, RunTransport, SenderOptions, TrajectorySender,
    TrajectoryStep, WeightsPublisher, WeightsReceiver,
};
use ctxrace_replay::{run, ReplayArgs, ReplayBuffer, ReplayControl};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::io::{BufReader, BufWriter, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::{mpsc, Arc, Barrier, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// What to measure.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IpcBenchOptions {
    /// Actor threads.
    pub actors: usize,
    /// Steps each actor sends.
    pub steps_per_actor: usize,
    /// Observation size (the default LiDAR has 108 beams).
    pub obs_dim: usize,
    /// Sequence batches requested (`batch x length`).
    pub batches: usize,
    /// `B`.
    pub batch: usize,
    /// `T`.
    pub length: usize,
    /// Weights size in bytes.
    pub weights_bytes: usize,
    /// Weights subscribers.
    pub subscribers: usize,
    /// Broadcasts timed.
    pub broadcasts: usize,
}

impl Default for IpcBenchOptions {
    fn default() -> Self {
        Self {
            actors: 4,
            steps_per_actor: 250_000,
            obs_dim: 108,
            batches: 50,
            batch: 16,
            length: 64,
            weights_bytes: 10 << 20,
            subscribers: 8,
            broadcasts: 20,
        }
    }
}

/// One transport's figures.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TransportFigures {
    /// Env steps per second into the replay buffer.
    pub steps_per_sec: f64,
    /// Median request-to-batch latency (ms).
    pub batch_ms_p50: f64,
    /// 90th percentile request-to-batch latency (ms).
    pub batch_ms_p90: f64,
    /// Median broadcast latency to the last subscriber (ms).
    pub broadcast_ms_p50: f64,
    /// 90th percentile broadcast latency (ms).
    pub broadcast_ms_p90: f64,
    /// Median time the learner spends sending one broadcast (ms).
    pub broadcast_send_ms_p50: f64,
    /// Median broadcast latency to a single subscriber (ms), measured over iceoryx2 only.
    pub broadcast_one_ms_p50: f64,
    /// Median send time of a broadcast to a single subscriber (ms): with more subscribers the
    /// learner's send shares the cores with their copies.
    pub broadcast_one_send_ms_p50: f64,
}

/// The benchmark's result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IpcBenchReport {
    /// What was measured.
    pub options: IpcBenchOptions,
    /// Over iceoryx2 shared memory.
    pub iceoryx2: TransportFigures,
    /// Over Unix domain sockets with bincode.
    pub uds_bincode: TransportFigures,
    /// iceoryx2 steps/s over the baseline's.
    pub steps_ratio: f64,
    /// Baseline batch latency over iceoryx2's (medians).
    pub batch_speedup: f64,
    /// Baseline broadcast latency over iceoryx2's (medians).
    pub broadcast_speedup: f64,
    /// Goal: at least 1M steps/s into replay.
    pub steps_goal_met: bool,
    /// Goal: broadcast under 3 ms (median).
    pub broadcast_goal_met: bool,
    /// Cores this process may run on.
    pub cores: usize,
    /// The broadcast's floor on these cores over iceoryx2 (ms): the publisher's send, then the
    /// subscribers' copies and checks, `cores` at a time, each as long as a single subscriber's
    /// (its latency less its send). Each subscriber copies the whole blob out of shared memory
    /// before it checks it: no scheduling beats this.
    pub broadcast_floor_ms: f64,
}

/// Runs the benchmark.
pub fn run_ipc_bench(opts: &IpcBenchOptions) -> Result<IpcBenchReport> {
    if opts.actors == 0 || opts.subscribers == 0 || opts.batches == 0 || opts.broadcasts == 0 {
        return Err(anyhow!(
            "actors, subscribers, batches and broadcasts must be positive"
        ));
    }
    let prefix = run_prefix(&format!("bench-{}", std::process::id()));
    let weights_prefix = run_prefix(&format!("bench-{}-weights", std::process::id()));
    let one_prefix = run_prefix(&format!("bench-{}-weights-one", std::process::id()));
    let ipc = iceoryx_figures(opts, &prefix, &weights_prefix, &one_prefix);
    let cleaned = cleanup(&prefix)
        .and(cleanup(&weights_prefix))
        .and(cleanup(&one_prefix));
    let ipc = ipc?;
    cleaned?;
    let uds = uds_figures(opts)?;
    let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { 0.0 };
    let cores = thread::available_parallelism().map_or(1, |n| n.get());
    let receive = (ipc.broadcast_one_ms_p50 - ipc.broadcast_one_send_ms_p50).max(0.0);
    Ok(IpcBenchReport {
        options: opts.clone(),
        steps_ratio: ratio(ipc.steps_per_sec, uds.steps_per_sec),
        batch_speedup: ratio(uds.batch_ms_p50, ipc.batch_ms_p50),
        broadcast_speedup: ratio(uds.broadcast_ms_p50, ipc.broadcast_ms_p50),
        steps_goal_met: ipc.steps_per_sec >= 1e6,
        broadcast_goal_met: ipc.broadcast_ms_p50 < 3.0,
        cores,
        broadcast_floor_ms: ipc.broadcast_one_send_ms_p50
            + receive * opts.subscribers.div_ceil(cores) as f64,
        iceoryx2: ipc,
        uds_bincode: uds,
    })
}

/// Synthetic steps of one actor: episodes of 500 steps.
fn synthetic(opts: &IpcBenchOptions, id: usize, k: usize, obs: &mut [f32]) -> (u64, bool, bool) {
    obs.iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v = ((k + i + id) % 97) as f32 * 0.01);
    let e = k % 500;
    (
        (k / 500) as u64,
        e == 0,
        e == 499 || k + 1 == opts.steps_per_actor,
    )
}

/// The step both transports send for observation `obs`.
fn synthetic_step(obs: &[f32], is_first: bool, is_last: bool) -> TrajectoryStep<'_> {
    TrajectoryStep {
        obs,
        action: &[0.1, -0.1],
        reward: 0.5,
        is_first,
        is_terminal: false,
        is_last,
        context: [0.0, 0.0],
        mask: Some([0.5, 0.5]),
    }
}

fn percentile(mut v: Vec<f64>, q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Steps the bench's replay buffers hold (the ring wraps past it).
const BENCH_CAPACITY: usize = 1 << 18;

/// Steps both transports' replay buffers hold: [`BENCH_CAPACITY`], or two batches' worth per
/// actor if more.
fn bench_capacity(opts: &IpcBenchOptions) -> usize {
    BENCH_CAPACITY.max(opts.batch * opts.length * opts.actors * 2)
}

/// The weights blob both transports broadcast.
fn weights_blob(bytes: usize) -> Vec<u8> {
    (0..bytes).map(|i| (i * 31) as u8).collect()
}

/// The iceoryx2 figures: steps and batches on `prefix`, broadcasts to the subscribers on
/// `weights_prefix` and to a single one on `one_prefix`; every message sealed and checked with a
/// fresh key, as in a run.
fn iceoryx_figures(
    opts: &IpcBenchOptions,
    prefix: &str,
    weights_prefix: &str,
    one_prefix: &str,
) -> Result<TransportFigures> {
    let key = RunKey::generate()?;
    let total = (opts.actors * opts.steps_per_actor) as u64;
    let args = ReplayArgs {
        prefix: prefix.to_string(),
        actors: opts.actors,
        obs_dim: opts.obs_dim,
        act_dim: 2,
        options: ReplayOptions {
            capacity: bench_capacity(opts),
            min_fill: 0,
            snapshot_every_secs: 0,
            snapshot_path: None,
            ..Default::default()
        },
        // the bench's actors send no weights version
        max_policy_version: 0,
        env_steps: u64::MAX,
        sampled_at_least: 0,
        handle_signals: false,
        streams_path: None,
    };
    let control = Arc::new(ReplayControl::default());
    let replay = {
        let (a, k, c) = (args.clone(), key.clone(), control.clone());
        thread::spawn(move || run(&a, &k, &c))
    };
    let result = iceoryx_measure(opts, prefix, &key, total, &control);
    control.shutdown.store(true, Ordering::Release);
    let status = replay
        .join()
        .map_err(|_| anyhow!("replay thread panicked"))??;
    let mut figures = result?;
    if status.inserted != total {
        return Err(anyhow!(
            "replay inserted {} of {total} steps",
            status.inserted
        ));
    }
    let (p50, p90, send) = iceoryx_broadcast(opts, weights_prefix, &key)?;
    figures.broadcast_ms_p50 = p50;
    figures.broadcast_ms_p90 = p90;
    figures.broadcast_send_ms_p50 = send;
    let one = IpcBenchOptions {
        subscribers: 1,
        ..opts.clone()
    };
    let (one_p50, _, one_send) = iceoryx_broadcast(&one, one_prefix, &key)?;
    figures.broadcast_one_ms_p50 = one_p50;
    figures.broadcast_one_send_ms_p50 = one_send;
    Ok(figures)
}

fn iceoryx_measure(
    opts: &IpcBenchOptions,
    prefix: &str,
    key: &RunKey,
    total: u64,
    control: &ReplayControl,
) -> Result<TransportFigures> {
    let barrier = Arc::new(Barrier::new(opts.actors + 1));
    let actors: Vec<_> = (0..opts.actors)
        .map(|id| {
            let (o, p, k, b) = (
                opts.clone(),
                prefix.to_string(),
                key.clone(),
                barrier.clone(),
            );
            thread::spawn(move || -> Result<u64> {
                let t = RunTransport::open(&p, o.actors, &format!("actor{id}"), &k)?;
                let mut tx =
                    TrajectorySender::new(&t, id as u32, o.obs_dim, 2, SenderOptions::default())?;
                let mut obs = vec![0.0; o.obs_dim];
                b.wait();
                for k in 0..o.steps_per_actor {
                    let (episode, first, last) = synthetic(&o, id, k, &mut obs);
                    tx.push(episode, 0, &synthetic_step(&obs, first, last))?;
                    // as an actor does: wait while the replay has no room
                    while tx.backlog() > 0 {
                        tx.deliver(Duration::from_millis(100))?;
                    }
                }
                Ok(tx.close()?.dropped_steps)
            })
        })
        .collect();
    barrier.wait();
    let start = Instant::now();
    let mut dropped = 0;
    for h in actors {
        dropped += h.join().map_err(|_| anyhow!("actor thread panicked"))??;
    }
    while control.inserted.load(Ordering::Acquire) + dropped < total {
        if start.elapsed() > Duration::from_secs(60) {
            return Err(anyhow!(
                "the replay took {} of {total} steps within 60 s ({dropped} dropped)",
                control.inserted.load(Ordering::Acquire)
            ));
        }
        thread::sleep(Duration::from_micros(200));
    }
    let steps_per_sec = total as f64 / start.elapsed().as_secs_f64();
    if dropped > 0 {
        return Err(anyhow!("{dropped} steps were dropped"));
    }

    let t = RunTransport::open(prefix, opts.actors, "learner", key)?;
    let mut client = ReplayClient::new(&t, opts.obs_dim, 2, Duration::from_secs(10))?;
    let spec = BatchSpec::Sequence {
        batch: opts.batch,
        length: opts.length,
    };
    let mut lat = Vec::new();
    for _ in 0..opts.batches {
        let start = Instant::now();
        match client.next_batch(spec, Duration::from_secs(10))? {
            Some(Batch::Sequence(_)) => lat.push(start.elapsed().as_secs_f64() * 1e3),
            _ => return Err(anyhow!("no batch from the replay within 10 s")),
        }
    }
    Ok(TransportFigures {
        steps_per_sec,
        batch_ms_p50: percentile(lat.clone(), 0.5),
        batch_ms_p90: percentile(lat, 0.9),
        ..Default::default()
    })
}

/// Weights broadcast latencies (p50, p90, send p50) in ms over iceoryx2, sealed with `key`.
fn iceoryx_broadcast(
    opts: &IpcBenchOptions,
    prefix: &str,
    key: &RunKey,
) -> Result<(f64, f64, f64)> {
    let t = RunTransport::open(prefix, opts.subscribers, "learner", key)?;
    let publisher = WeightsPublisher::new(&t, opts.weights_bytes)?;
    let base = Instant::now();
    let (done_tx, done_rx) = mpsc::channel::<Result<(u64, f64)>>();
    let barrier = Arc::new(Barrier::new(opts.subscribers + 1));
    let subs: Vec<_> = (0..opts.subscribers)
        .map(|i| {
            let (p, k, n, b, done) = (
                prefix.to_string(),
                key.clone(),
                opts.subscribers,
                barrier.clone(),
                done_tx.clone(),
            );
            let rounds = opts.broadcasts;
            thread::spawn(move || {
                let run = || -> Result<()> {
                    let t = RunTransport::open(&p, n, &format!("actor{i}"), &k)?;
                    let mut rx = WeightsReceiver::new(&t, rounds as u64)?;
                    b.wait();
                    let mut got = 0;
                    while got < rounds {
                        let r =
                            rx.wait_with(Duration::from_secs(10), |v, bytes| (v, bytes.len()))?;
                        let Some((version, _)) = r else {
                            return Err(anyhow!("subscriber {i} got no weights within 10 s"));
                        };
                        let _ = done.send(Ok((version, base.elapsed().as_secs_f64() * 1e3)));
                        got += 1;
                    }
                    Ok(())
                };
                if let Err(e) = run() {
                    let _ = done.send(Err(e));
                }
            })
        })
        .collect();
    barrier.wait();
    let weights = weights_blob(opts.weights_bytes);
    let (mut lat, mut send) = (Vec::new(), Vec::new());
    for version in 1..=opts.broadcasts as u64 {
        let sent = base.elapsed().as_secs_f64() * 1e3;
        publisher.publish(version, &weights)?;
        send.push(base.elapsed().as_secs_f64() * 1e3 - sent);
        let mut last = 0.0f64;
        for _ in 0..opts.subscribers {
            let (v, at) = done_rx
                .recv_timeout(Duration::from_secs(20))
                .context("a weights subscriber stalled")??;
            if v != version {
                return Err(anyhow!("subscriber got version {v}, expected {version}"));
            }
            last = last.max(at);
        }
        lat.push(last - sent);
    }
    for s in subs {
        s.join()
            .map_err(|_| anyhow!("subscriber thread panicked"))?;
    }
    Ok((
        percentile(lat.clone(), 0.5),
        percentile(lat, 0.9),
        percentile(send, 0.5),
    ))
}

/// A chunk as the baseline sends it.
#[derive(Serialize, Deserialize)]
struct UdsChunk {
    actor: u32,
    steps: u32,
    payload: Vec<f32>,
}

/// A weights blob as the baseline sends it.
#[derive(Serialize, Deserialize)]
struct UdsWeights {
    version: u64,
    checksum: u32,
    bytes: Vec<u8>,
}

/// A sequence batch as the baseline sends it.
#[derive(Serialize, Deserialize)]
struct UdsBatch {
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: Vec<f32>,
    is_first: Vec<f32>,
    is_terminal: Vec<f32>,
    context: Vec<f32>,
    mask: Vec<f32>,
    has_mask: Vec<f32>,
}

/// A sampled batch's fields, moved into the baseline's frame.
impl From<SequenceBatch> for UdsBatch {
    fn from(s: SequenceBatch) -> Self {
        Self {
            obs: s.obs,
            action: s.action,
            reward: s.reward,
            is_first: s.is_first,
            is_terminal: s.is_terminal,
            context: s.context,
            mask: s.mask,
            has_mask: s.has_mask,
        }
    }
}

fn send_frame<W: Write, T: Serialize>(w: &mut W, value: &T) -> Result<()> {
    let bytes = bincode::serialize(value)?;
    w.write_all(&(bytes.len() as u64).to_le_bytes())?;
    w.write_all(&bytes)?;
    Ok(())
}

fn recv_frame<R: Read, T: for<'de> Deserialize<'de>>(r: &mut R) -> Result<Option<T>> {
    let mut len = [0u8; 8];
    match r.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e.into()),
    }
    let mut bytes = vec![0u8; u64::from_le_bytes(len) as usize];
    r.read_exact(&mut bytes)?;
    Ok(Some(bincode::deserialize(&bytes)?))
}

/// The baseline's figures: the same steps, batches and broadcasts over Unix domain sockets
/// (in a temporary directory) with bincode.
fn uds_figures(opts: &IpcBenchOptions) -> Result<TransportFigures> {
    let dir = tempfile::tempdir()?;
    let buffer = Arc::new(Mutex::new(ReplayBuffer::new(
        bench_capacity(opts),
        opts.actors,
        opts.obs_dim,
        2,
    )));
    let steps_per_sec = uds_steps(opts, &dir.path().join("steps.sock"), &buffer)?;
    let lat = uds_batches(opts, &dir.path().join("batch.sock"), &buffer)?;
    let (blat, bsend) = uds_broadcast(opts, &dir.path().join("weights.sock"))?;
    Ok(TransportFigures {
        steps_per_sec,
        batch_ms_p50: percentile(lat.clone(), 0.5),
        batch_ms_p90: percentile(lat, 0.9),
        broadcast_ms_p50: percentile(blat.clone(), 0.5),
        broadcast_ms_p90: percentile(blat, 0.9),
        broadcast_send_ms_p50: percentile(bsend, 0.5),
        ..Default::default()
    })
}

/// Env steps per second from the actors into `buffer` over the socket at `path`: one
/// connection per actor, one replay thread per connection.
fn uds_steps(
    opts: &IpcBenchOptions,
    path: &Path,
    buffer: &Arc<Mutex<ReplayBuffer>>,
) -> Result<f64> {
    let total = opts.actors * opts.steps_per_actor;
    let listener = UnixListener::bind(path)?;
    let server = uds_step_server(listener, buffer.clone(), opts.actors);
    let barrier = Arc::new(Barrier::new(opts.actors + 1));
    let actors: Vec<_> = (0..opts.actors)
        .map(|id| {
            let (opts, path, b) = (opts.clone(), path.to_path_buf(), barrier.clone());
            thread::spawn(move || uds_actor(&opts, id, &path, &b))
        })
        .collect();
    barrier.wait();
    let start = Instant::now();
    for h in actors {
        h.join().map_err(|_| anyhow!("actor panicked"))??;
    }
    server.join().map_err(|_| anyhow!("server panicked"))??;
    let steps_per_sec = total as f64 / start.elapsed().as_secs_f64();
    let inserted = buffer.lock().map_err(|_| anyhow!("poisoned"))?.inserted();
    if inserted != total as u64 {
        return Err(anyhow!("socket replay inserted {inserted} of {total}"));
    }
    Ok(steps_per_sec)
}

/// The baseline's replay side of the steps: accepts `actors` connections on `listener` and
/// reads each on a thread of its own until all have closed.
fn uds_step_server(
    listener: UnixListener,
    buffer: Arc<Mutex<ReplayBuffer>>,
    actors: usize,
) -> thread::JoinHandle<Result<()>> {
    thread::spawn(move || -> Result<()> {
        let readers: Vec<_> = (0..actors)
            .map(|_| {
                let (stream, _) = listener.accept()?;
                let buffer = buffer.clone();
                Ok(thread::spawn(move || uds_insert_chunks(stream, &buffer)))
            })
            .collect::<Result<_>>()?;
        for r in readers {
            r.join().map_err(|_| anyhow!("reader panicked"))??;
        }
        Ok(())
    })
}

/// Inserts the chunks an actor sends on `stream` into `buffer` until it closes the stream.
fn uds_insert_chunks(stream: UnixStream, buffer: &Mutex<ReplayBuffer>) -> Result<()> {
    let mut r = BufReader::with_capacity(1 << 20, stream);
    let mut first = true;
    while let Some(c) = recv_frame::<_, UdsChunk>(&mut r)? {
        let lock = buffer.lock();
        let mut b = lock.map_err(|_| anyhow!("poisoned"))?;
        b.insert_chunk(c.actor as usize, &c.payload, first);
        first = false;
    }
    Ok(())
}

/// Actor `id` of the baseline: once `barrier` opens, sends its synthetic steps to the socket at
/// `path` in chunks as the transport's, one bincode frame each.
fn uds_actor(opts: &IpcBenchOptions, id: usize, path: &Path, barrier: &Barrier) -> Result<()> {
    let mut w = BufWriter::new(UnixStream::connect(path)?);
    let stride = step_stride(opts.obs_dim, 2);
    let mut obs = vec![0.0; opts.obs_dim];
    let mut chunk = Vec::with_capacity(MAX_CHUNK * stride);
    let mut steps = 0u32;
    barrier.wait();
    for k in 0..opts.steps_per_actor {
        let (_, first, last) = synthetic(opts, id, k, &mut obs);
        synthetic_step(&obs, first, last).encode(&mut chunk);
        steps += 1;
        if last || steps as usize == MAX_CHUNK {
            let c = UdsChunk {
                actor: id as u32,
                steps,
                payload: std::mem::take(&mut chunk),
            };
            send_frame(&mut w, &c)?;
            chunk.reserve(MAX_CHUNK * stride);
            steps = 0;
        }
    }
    w.flush()?;
    Ok(())
}

/// Request-to-batch latencies (ms) of the baseline's sequence batches from `buffer`, over the
/// socket at `path`: request, sample, serialise, answer.
fn uds_batches(
    opts: &IpcBenchOptions,
    path: &Path,
    buffer: &Arc<Mutex<ReplayBuffer>>,
) -> Result<Vec<f64>> {
    let listener = UnixListener::bind(path)?;
    let server = uds_batch_server(listener, buffer.clone());
    let stream = UnixStream::connect(path)?;
    let mut r = BufReader::new(stream.try_clone()?);
    let mut w = BufWriter::new(stream);
    let mut lat = Vec::new();
    for _ in 0..opts.batches {
        let start = Instant::now();
        send_frame(&mut w, &(opts.batch as u32, opts.length as u32))?;
        w.flush()?;
        let b: UdsBatch = recv_frame(&mut r)?.ok_or_else(|| anyhow!("batch server closed"))?;
        if b.obs.len() != opts.batch * opts.length * opts.obs_dim {
            return Err(anyhow!("bad batch"));
        }
        lat.push(start.elapsed().as_secs_f64() * 1e3);
    }
    drop(w);
    drop(r);
    server.join().map_err(|_| anyhow!("server panicked"))??;
    Ok(lat)
}

/// The baseline's batch server: answers each `(B, T)` request of the one connection on
/// `listener` with sequences sampled from `buffer`, until the learner closes it.
fn uds_batch_server(
    listener: UnixListener,
    buffer: Arc<Mutex<ReplayBuffer>>,
) -> thread::JoinHandle<Result<()>> {
    thread::spawn(move || -> Result<()> {
        let (stream, _) = listener.accept()?;
        let mut r = BufReader::new(stream.try_clone()?);
        let mut w = BufWriter::new(stream);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        while let Some((b, t)) = recv_frame::<_, (u32, u32)>(&mut r)? {
            let s: SequenceBatch = buffer
                .lock()
                .map_err(|_| anyhow!("poisoned"))?
                .sample_sequences(b as usize, t as usize, &mut rng)
                .ok_or_else(|| anyhow!("no sequences"))?;
            send_frame(&mut w, &UdsBatch::from(s))?;
            w.flush()?;
        }
        Ok(())
    })
}

/// Broadcast latencies to the last subscriber and send times (ms) of the baseline, over the
/// socket at `path`: the learner writes to each subscriber's connection in turn.
fn uds_broadcast(opts: &IpcBenchOptions, path: &Path) -> Result<(Vec<f64>, Vec<f64>)> {
    let listener = UnixListener::bind(path)?;
    let base = Instant::now();
    let (done_tx, done_rx) = mpsc::channel::<Result<(u64, f64)>>();
    let subs: Vec<_> = (0..opts.subscribers)
        .map(|_| {
            let (path, done) = (path.to_path_buf(), done_tx.clone());
            thread::spawn(move || {
                if let Err(e) = uds_subscriber(&path, base, &done) {
                    let _ = done.send(Err(e));
                }
            })
        })
        .collect();
    let mut conns: Vec<_> = (0..opts.subscribers)
        .map(|_| Ok(BufWriter::with_capacity(1 << 20, listener.accept()?.0)))
        .collect::<Result<_>>()?;
    let bytes = weights_blob(opts.weights_bytes);
    let (mut blat, mut bsend) = (Vec::new(), Vec::new());
    for version in 1..=opts.broadcasts as u64 {
        let sent = base.elapsed().as_secs_f64() * 1e3;
        let wts = UdsWeights {
            version,
            checksum: crc32fast::hash(&bytes),
            bytes: bytes.clone(),
        };
        for c in conns.iter_mut() {
            send_frame(c, &wts)?;
            c.flush()?;
        }
        bsend.push(base.elapsed().as_secs_f64() * 1e3 - sent);
        let mut last = 0.0f64;
        for _ in 0..opts.subscribers {
            let (v, at) = done_rx
                .recv_timeout(Duration::from_secs(20))
                .context("a socket subscriber stalled")??;
            if v != version {
                return Err(anyhow!("socket subscriber got version {v}"));
            }
            last = last.max(at);
        }
        blat.push(last - sent);
    }
    drop(conns);
    for s in subs {
        s.join().map_err(|_| anyhow!("subscriber panicked"))?;
    }
    Ok((blat, bsend))
}

/// A subscriber of the baseline: checks each weights blob that arrives on the socket at `path`
/// and reports its version and arrival (ms after `base`) on `done`, until the learner closes.
fn uds_subscriber(
    path: &Path,
    base: Instant,
    done: &mpsc::Sender<Result<(u64, f64)>>,
) -> Result<()> {
    let mut r = BufReader::with_capacity(1 << 20, UnixStream::connect(path)?);
    while let Some(wts) = recv_frame::<_, UdsWeights>(&mut r)? {
        if crc32fast::hash(&wts.bytes) != wts.checksum {
            return Err(anyhow!("checksum mismatch"));
        }
        let _ = done.send(Ok((wts.version, base.elapsed().as_secs_f64() * 1e3)));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_bench_runs_both_transports() {
        let opts = IpcBenchOptions {
            actors: 2,
            steps_per_actor: 2000,
            obs_dim: 16,
            batches: 3,
            batch: 2,
            length: 8,
            weights_bytes: 64 << 10,
            subscribers: 2,
            broadcasts: 3,
        };
        let r = run_ipc_bench(&opts).unwrap();
        assert!(r.iceoryx2.steps_per_sec > 0.0 && r.uds_bincode.steps_per_sec > 0.0);
        assert!(r.iceoryx2.broadcast_ms_p50 > 0.0 && r.uds_bincode.batch_ms_p50 > 0.0);
    }
}
