//! The replay process loop: chunks in, batches out when the rate limiter allows, status out,
//! snapshots periodically and on shutdown. Every turn ends with a beacon signal (closing actors
//! wait for one). Between turns it sleeps on the run's `wake_replay` event, at most a 100 ms
//! tick ([`RunTransport::serve`]), so it returns on SIGTERM/SIGINT too.

use crate::buffer::ReplayBuffer;
use crate::limiter::RateLimiter;
use crate::snapshot::{
    check_snapshot, encode_snapshot, read_snapshot, write_snapshot, BackgroundWriter,
    LimiterCounts, SnapshotError, SnapshotShape,
};
use ctxrace_config::validate::ConfigError;
use ctxrace_config::BatchSpec;
use ctxrace_config::ReplayOptions;
use ctxrace_ipc::wire::{ReplayStatus, WireError, FORMAT_VERSION, MAX_PENDING_REQUESTS, REASONS};
use ctxrace_ipc::{
    BatchRequest, BatchServer, ChunkView, IpcError, Next, ReplayBeacon, RunKey, RunTransport,
    StatusPublisher, TrajectoryReceiver, Wake,
};
use ctxrace_run::results::ReplayStreams;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// Chunks taken per loop turn before requests are looked at again.
const CHUNKS_PER_TURN: usize = 256;
/// Longest sleep of the loop.
const TICK: Duration = Duration::from_millis(100);
/// Seconds between status messages.
const STATUS_EVERY: Duration = Duration::from_secs(1);
/// Longest the replay waits, when stopping, for the actors' senders to close.
const DRAIN_LIMIT: Duration = Duration::from_secs(10);

/// Why the replay loop stopped on an error.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The run's snapshot cannot be restored (damaged, or of another run): a restart would meet
    /// it again, so its cause is a [`ConfigError`]; the message says how to continue.
    #[error(
        "the replay cannot start from its snapshot; to continue the run with an empty replay \
         (the learner keeps its checkpoints), move the file away (mv {p} {p}.damaged) and \
         continue the run (`ctxrace train … --resume`)",
        p = .path.display()
    )]
    Restore {
        /// The snapshot file.
        path: PathBuf,
        /// Why it cannot be restored (a [`SnapshotError`], marked).
        #[source]
        source: ConfigError,
    },
    /// A snapshot could not be written.
    #[error(transparent)]
    Snapshot(#[from] SnapshotError),
    /// The transport failed.
    #[error(transparent)]
    Ipc(#[from] IpcError),
}

/// What the replay process serves.
#[derive(Clone, Debug)]
pub struct ReplayArgs {
    /// The run's iceoryx2 prefix.
    pub prefix: String,
    /// Actors in the run.
    pub actors: usize,
    /// Observation size (one frame).
    pub obs_dim: usize,
    /// Action size.
    pub act_dim: usize,
    /// Buffer, limiter and snapshot settings.
    pub options: ReplayOptions,
    /// The newest weights version a chunk may name: the learner's gradient-step target.
    pub max_policy_version: u64,
    /// The run's env-step budget (`[train] env_steps`): the replay stores at most this many
    /// steps in all (restored ones included) and counts what arrives past it as surplus.
    pub env_steps: u64,
    /// Steps the learner has certainly sampled: its newest checkpoint's gradient steps times
    /// the steps of a batch. A restored snapshot older than that checkpoint counts at least
    /// these, so that the rate limiter holds the resumed learner to the inserts it had (with
    /// the snapshot's count, it finished a resumed run 4,107 steps short of its 24,000).
    pub sampled_at_least: u64,
    /// Stop on SIGTERM/SIGINT (a process); false when run on a thread.
    pub handle_signals: bool,
    /// Where to write the steps stored of each actor each second
    /// ([`ctxrace_run::run_dir::REPLAY_STREAMS`], for the launcher's liveness check); none on
    /// a thread.
    pub streams_path: Option<std::path::PathBuf>,
}

/// Shared with whoever runs the loop on a thread: a stop flag and live counters.
#[derive(Debug, Default)]
pub struct ReplayControl {
    /// Set to stop the loop (it notices within [`TICK`]).
    pub shutdown: AtomicBool,
    /// Steps inserted so far, updated every loop turn.
    pub inserted: AtomicU64,
    /// Set once the endpoints exist and the replay was announced.
    pub ready: AtomicBool,
}

/// What the replay loop counts besides its buffer, limiter, receiver and server.
#[derive(Default)]
struct Counters {
    batches: u64,
    /// Requests that could never be served (they would block the queue forever) or found the
    /// queue full.
    unservable: u64,
    inserted_at_last_batch: u64,
    /// The longest turn of the loop (everything but its sleep): how long batch delivery can
    /// stall.
    longest_turn: Duration,
    restored_inserts: u64,
}

impl Counters {
    /// Refuses `request` for `spec`, which can never be served (`why`), telling the learner so.
    fn refuse(
        &mut self,
        server: &BatchServer,
        request: BatchRequest,
        spec: BatchSpec,
        why: &str,
    ) -> Result<(), IpcError> {
        self.unservable += 1;
        tracing::warn!(
            "refused batch request {} for {spec:?} ({} so far): {why}",
            request.request_id,
            self.unservable
        );
        let unservable = WireError::Unservable {
            steps: spec.steps() as u64,
        };
        server.refuse(&request, unservable.reason())?;
        Ok(())
    }

    /// The status to publish.
    fn status(
        &self,
        buffer: &ReplayBuffer,
        limiter: &RateLimiter,
        chunks: &TrajectoryReceiver,
        server: &BatchServer,
        pending: usize,
    ) -> ReplayStatus {
        let (c, r) = (chunks.rejected_by_reason(), server.rejected_by_reason());
        let mut by_reason: [u64; REASONS.len()] = std::array::from_fn(|i| c[i] + r[i]);
        by_reason[WireError::Unservable { steps: 0 }.reason()] += self.unservable;
        ReplayStatus {
            format_version: FORMAT_VERSION,
            longest_turn_us: self.longest_turn.as_micros().min(u32::MAX as u128) as u32,
            inserted: limiter.inserts(),
            sampled: limiter.samples(),
            fill: buffer.len() as u64,
            capacity: buffer.capacity() as u64,
            dropped_chunks: chunks.missing_chunks(),
            rejected: by_reason.iter().sum(),
            batches: self.batches,
            pending_requests: pending as u64,
            inserted_at_last_batch: self.inserted_at_last_batch,
            restored_inserts: self.restored_inserts,
            rejected_by_reason: by_reason,
            // the publisher sets the process id and the seal
            ..ReplayStatus::default()
        }
    }
}

/// The run's env-step budget: the replay stores at most `limit` steps in all. Once it has, it
/// takes no chunk until it stops (the actors wait, idle), then takes what they queued and counts
/// it, by actor, without storing it. The rate limiter is closed then: no more inserts will come,
/// so the learner takes its last gradient steps on the final data instead of waiting for steps
/// that never arrive.
struct Budget {
    limit: u64,
    /// Steps that arrived past the budget, by actor.
    surplus: Vec<u64>,
}

impl Budget {
    fn new(limit: u64, actors: usize) -> Self {
        Self {
            limit,
            surplus: vec![0; actors],
        }
    }

    /// Whether the whole budget is stored.
    fn spent(&self, limiter: &RateLimiter) -> bool {
        limiter.inserts() >= self.limit
    }

    /// Closes `limiter` if the budget is stored (a restored snapshot may hold all of it).
    fn close_if_spent(&self, limiter: &mut RateLimiter) {
        if self.spent(limiter) && !limiter.is_closed() {
            limiter.close();
            tracing::info!(
                "replay: the run's {} env steps are stored; no chunk is taken until the replay \
                 stops, and what the actors queued is then counted as surplus",
                self.limit
            );
        }
    }

    /// Stores the steps of chunk `c` that fit in the budget; counts the rest as surplus.
    fn store(&mut self, c: ChunkView<'_>, buffer: &mut ReplayBuffer, limiter: &mut RateLimiter) {
        let actor = c.header.actor_id as usize;
        let steps = u64::from(c.header.steps);
        let room = self.limit.saturating_sub(limiter.inserts()).min(steps);
        if room > 0 {
            let stride = c.payload.len() / c.header.steps.max(1) as usize;
            buffer.insert_chunk(actor, &c.payload[..room as usize * stride], c.after_gap);
            limiter.inserted(room);
        }
        if let Some(surplus) = self.surplus.get_mut(actor) {
            *surplus += steps - room;
        }
        self.close_if_spent(limiter);
    }
}

/// Runs the replay of the run with key `key` until `control.shutdown` is set or (with
/// `handle_signals`) SIGTERM/SIGINT; writes a final snapshot and returns the final counters.
pub fn run(
    args: &ReplayArgs,
    key: &RunKey,
    control: &ReplayControl,
) -> Result<ReplayStatus, ReplayError> {
    let opts = &args.options;
    let (mut buffer, counts) = restore(args)?;
    let mut limiter = RateLimiter::new(
        opts.samples_per_insert,
        opts.min_fill as u64,
        opts.error_buffer_steps,
    );
    limiter.restore(
        counts.inserts,
        restored_samples(&counts, args.sampled_at_least),
    );
    let mut budget = Budget::new(args.env_steps, args.actors);
    budget.close_if_spent(&mut limiter);
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed ^ counts.samples);

    let transport = RunTransport::open(&args.prefix, args.actors, "replay", key)?;
    let mut chunks = TrajectoryReceiver::new(
        &transport,
        args.obs_dim,
        args.act_dim,
        args.max_policy_version,
    )?;
    let mut server = BatchServer::new(
        &transport,
        args.obs_dim,
        args.act_dim,
        opts.max_batch_floats,
    )?;
    let status = StatusPublisher::new(&transport)?;
    let beacon = ReplayBeacon::new(&transport)?;
    beacon.signal();
    control.ready.store(true, Ordering::Release);
    tracing::info!(
        "replay up: prefix {}, {} actors, {} of {} steps held",
        args.prefix,
        args.actors,
        buffer.len(),
        buffer.capacity()
    );

    let mut pending: VecDeque<(BatchRequest, BatchSpec)> = VecDeque::new();
    let mut counters = Counters {
        restored_inserts: counts.inserts,
        ..Counters::default()
    };
    let mut last_status = Instant::now();
    let mut last_snapshot = Instant::now();
    let mut writer = BackgroundWriter::default();
    let signalled = transport.serve(Wake::Replay, TICK, args.handle_signals, || {
        let turn = Instant::now();
        // The limiter is asked before every chunk: too fast actors wait in backpressure.
        let mut taken = 0;
        // Once the budget is stored, no chunk is taken until the replay stops: the actors wait,
        // idle, and what they queued meanwhile is taken then (and counted as surplus).
        while taken < CHUNKS_PER_TURN && !budget.spent(&limiter) && limiter.can_insert(1) {
            let got = chunks.receive(1, |c| budget.store(c, &mut buffer, &mut limiter))?;
            if got == 0 {
                break;
            }
            taken += got;
        }
        control.inserted.store(limiter.inserts(), Ordering::Release);
        // Closing actors wait for a turn after their last send (see TrajectorySender).
        beacon.signal();
        for (request, spec) in server.receive_requests()? {
            // a learner sends a request again when its answer is long in coming: one waiting
            // already is not queued twice
            if pending.iter().any(|(r, _)| *r == request) {
                continue;
            }
            match never_served(spec, &buffer, &limiter, pending.len()) {
                None => pending.push_back((request, spec)),
                Some(why) => counters.refuse(&server, request, spec, &why)?,
            }
        }
        while let Some(&(request, spec)) = pending.front() {
            let n = spec.steps() as u64;
            if !limiter.can_sample(n) {
                break;
            }
            let sent = match spec {
                BatchSpec::Sequence { batch, length } => buffer
                    .sample_sequences_by(opts.sampler, batch, length, &mut rng)
                    .map(|b| server.send_sequence(&request, &b)),
                BatchSpec::Transition {
                    batch,
                    frames,
                    reward_delay,
                } => buffer
                    .sample_transitions(batch, frames, reward_delay, &mut rng)
                    .map(|b| server.send_transition(&request, frames, &b)),
            };
            match sent {
                Some(result) => {
                    result?;
                    limiter.sampled(n);
                    counters.batches += 1;
                    counters.inserted_at_last_batch = limiter.inserts();
                    pending.pop_front();
                }
                // Not enough contiguous data, and none will come: refuse it.
                None if limiter.is_closed() => {
                    let why = "the run's env steps are all stored and hold no such batch";
                    counters.refuse(&server, request, spec, why)?;
                    pending.pop_front();
                }
                // Not enough contiguous data yet: keep the request for a later turn.
                None => break,
            }
        }
        if last_status.elapsed() >= STATUS_EVERY {
            let s = counters.status(&buffer, &limiter, &chunks, &server, pending.len());
            status.publish(s)?;
            write_streams(args, &chunks, &budget, &limiter);
            last_status = Instant::now();
        }
        if opts.snapshot_every_secs > 0
            && last_snapshot.elapsed() >= Duration::from_secs(opts.snapshot_every_secs)
            && !writer.busy()
        {
            if let Some(path) = opts.snapshot_path.as_deref() {
                let start = Instant::now();
                let bytes = encode_snapshot(&buffer, limiter_counts(&limiter));
                let encoded = start.elapsed();
                writer.start(path.to_path_buf(), bytes)?;
                tracing::info!(
                    "replay: snapshot of {} steps encoded in {encoded:.2?}, written to {} in the \
                     background",
                    buffer.len(),
                    path.display()
                );
            }
            last_snapshot = Instant::now();
        }
        counters.longest_turn = counters.longest_turn.max(turn.elapsed());
        Ok::<_, ReplayError>(if control.shutdown.load(Ordering::Acquire) {
            Next::Stop
        } else if taken == CHUNKS_PER_TURN {
            // busy (a full turn of chunks taken): only poll
            Next::Poll
        } else {
            Next::Sleep
        })
    })?;
    if signalled {
        tracing::info!("replay: termination requested");
    }
    // the actors' last chunks are stored whatever the limiter says (up to the budget, the rest
    // counted as surplus), until every sender has closed (a killed actor's sender lingers: at
    // most DRAIN_LIMIT): nothing sent is lost uncounted
    let deadline = Instant::now() + DRAIN_LIMIT;
    loop {
        let got = chunks.receive(CHUNKS_PER_TURN, |c| {
            budget.store(c, &mut buffer, &mut limiter)
        })?;
        beacon.signal();
        if got == 0 {
            if chunks.senders() == 0 || Instant::now() >= deadline {
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }
    let last = counters.status(&buffer, &limiter, &chunks, &server, pending.len());
    status.publish(last)?;
    write_streams(args, &chunks, &budget, &limiter);
    writer.wait()?;
    snapshot(args, &buffer, &limiter)?;
    Ok(last)
}

/// Writes the steps this start stored of each actor, those past the budget, and the chunks it
/// rejected of each, with the steps stored in all (restored ones included) and the budget, to
/// `args.streams_path`, if any; advisory, like the status: a failed write costs the launcher
/// one look.
fn write_streams(
    args: &ReplayArgs,
    chunks: &TrajectoryReceiver,
    budget: &Budget,
    limiter: &RateLimiter,
) {
    if let Some(path) = &args.streams_path {
        let streams = ReplayStreams {
            stored_by_actor: (chunks.taken_steps().iter().zip(&budget.surplus))
                .map(|(taken, surplus)| taken.saturating_sub(*surplus))
                .collect(),
            surplus_by_actor: budget.surplus.clone(),
            rejected_by_actor: chunks.rejected_by_actor().to_vec(),
            inserted: limiter.inserts(),
            env_steps: budget.limit,
        };
        if let Err(e) = ctxrace_run::results::write_json(path, &streams) {
            tracing::warn!("replay: writing {}: {e}", path.display());
        }
    }
}

/// Why a request for `spec` would block the queue forever, or why it finds no room in it
/// (holding `pending` requests); `None` if it may wait in the queue.
fn never_served(
    spec: BatchSpec,
    buffer: &ReplayBuffer,
    limiter: &RateLimiter,
    pending: usize,
) -> Option<String> {
    let window = match spec {
        BatchSpec::Sequence { length, .. } => length,
        BatchSpec::Transition { reward_delay, .. } => 2 + reward_delay,
    };
    if !limiter.can_ever_sample(spec.steps() as u64) {
        Some(format!(
            "its {} steps exceed the rate limiter's window; raise [replay] error_buffer_steps \
             or lower the batch",
            spec.steps()
        ))
    } else if window > buffer.longest_window() {
        Some(format!(
            "its windows of {window} steps exceed each actor's ring of {} steps; raise \
             [replay] capacity or lower the sequence length",
            buffer.longest_window()
        ))
    } else if pending >= MAX_PENDING_REQUESTS {
        Some(format!(
            "{MAX_PENDING_REQUESTS} requests wait already (a learner has one outstanding)"
        ))
    } else {
        None
    }
}

/// Checks, before any process starts, that the replay of `args` could restore its snapshot (if
/// it has one): a damaged snapshot, or one of another shape, is the [`ReplayError::Restore`]
/// the replay would stop on, saying how to continue.
pub fn check_restorable(args: &ReplayArgs) -> Result<(), ReplayError> {
    let Some(path) = args.options.snapshot_path.as_deref() else {
        return Ok(());
    };
    if !path.exists() {
        return Ok(());
    }
    let o = &args.options;
    let shape = SnapshotShape::of_new(o.capacity, args.actors, args.obs_dim, args.act_dim);
    check_snapshot(path, shape).map_err(|e| ReplayError::Restore {
        path: path.to_path_buf(),
        source: ConfigError::new(e),
    })
}

/// The replay's buffer and limiter counts: fresh, or restored from the snapshot. A snapshot
/// that cannot be read, or whose shape is not the run's, is a [`ReplayError::Restore`] (a
/// [`ConfigError`]: a restarted replay would meet it again) saying how to continue.
fn restore(args: &ReplayArgs) -> Result<(ReplayBuffer, LimiterCounts), ReplayError> {
    let fresh = ReplayBuffer::new(
        args.options.capacity,
        args.actors,
        args.obs_dim,
        args.act_dim,
    );
    let none = LimiterCounts {
        inserts: 0,
        samples: 0,
    };
    let Some(path) = args.options.snapshot_path.as_deref() else {
        return Ok((fresh, none));
    };
    if !path.exists() {
        return Ok((fresh, none));
    }
    let (buffer, counts) =
        read_snapshot(path, SnapshotShape::of(&fresh)).map_err(|e| ReplayError::Restore {
            path: path.to_path_buf(),
            source: ConfigError::new(e),
        })?;
    tracing::info!(
        "replay: restored {} steps from {}",
        buffer.len(),
        path.display()
    );
    Ok((buffer, counts))
}

/// The samples a restored limiter counts: the snapshot's, or `sampled_at_least` where the
/// learner's checkpoint is newer; a fresh buffer (nothing restored) starts the ratio over.
fn restored_samples(counts: &LimiterCounts, sampled_at_least: u64) -> u64 {
    match counts.inserts {
        0 => counts.samples,
        _ => counts.samples.max(sampled_at_least),
    }
}

fn limiter_counts(limiter: &RateLimiter) -> LimiterCounts {
    LimiterCounts {
        inserts: limiter.inserts(),
        samples: limiter.samples(),
    }
}

fn snapshot(
    args: &ReplayArgs,
    buffer: &ReplayBuffer,
    limiter: &RateLimiter,
) -> Result<(), SnapshotError> {
    if let Some(path) = args.options.snapshot_path.as_deref() {
        let start = Instant::now();
        write_snapshot(path, buffer, limiter_counts(limiter))?;
        tracing::info!(
            "replay: snapshot of {} steps to {} in {:.2?}",
            buffer.len(),
            path.display(),
            start.elapsed()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_restored_limiter_counts_at_least_the_learners_checkpointed_samples() {
        let counts = |inserts, samples| LimiterCounts { inserts, samples };
        // the snapshot is older than the checkpoint: the checkpoint's count
        assert_eq!(restored_samples(&counts(11_204, 70_000), 97_280), 97_280);
        // the snapshot is newer: its own
        assert_eq!(restored_samples(&counts(11_204, 99_000), 97_280), 99_000);
        // nothing restored: the ratio starts over
        assert_eq!(restored_samples(&counts(0, 0), 97_280), 0);
    }

    #[test]
    fn requests_that_could_never_be_served_or_find_the_queue_full_are_refused_with_the_reason() {
        // 40 steps shared by 2 actors: rings of 20
        let buffer = ReplayBuffer::new(40, 2, 3, 2);
        let free = RateLimiter::new(0.0, 0, 0.0);
        let sequences = |length| BatchSpec::Sequence { batch: 4, length };
        assert_eq!(never_served(sequences(20), &buffer, &free, 0), None);
        let why = never_served(sequences(32), &buffer, &free, 0).unwrap();
        assert!(
            why.contains("windows of 32 steps exceed each actor's ring of 20"),
            "{why}"
        );
        assert!(why.contains("raise [replay] capacity"), "{why}");
        // a window of 2 · 10 · 1 = 20 samples holds no batch of 4 x 20
        let tight = RateLimiter::new(1.0, 0, 10.0);
        let why = never_served(sequences(20), &buffer, &tight, 0).unwrap();
        assert!(why.contains("rate limiter's window"), "{why}");
        let why = never_served(sequences(20), &buffer, &free, MAX_PENDING_REQUESTS).unwrap();
        assert!(why.contains("requests wait already"), "{why}");
    }

    #[test]
    fn a_damaged_snapshot_is_a_config_error_saying_how_to_continue() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.snapshot");
        std::fs::write(&path, b"CTXRPLY\0 not a snapshot").unwrap();
        let args = ReplayArgs {
            prefix: String::new(),
            actors: 1,
            obs_dim: 3,
            act_dim: 2,
            options: ReplayOptions {
                capacity: 100,
                snapshot_path: Some(path),
                ..ReplayOptions::default()
            },
            max_policy_version: 0,
            env_steps: u64::MAX,
            sampled_at_least: 0,
            handle_signals: false,
            streams_path: None,
        };
        let Err(err) = restore(&args) else {
            panic!("a damaged snapshot is refused");
        };
        let chain = std::iter::successors(Some(&err as &dyn std::error::Error), |e| e.source());
        assert_eq!(chain.filter(|e| e.is::<ConfigError>()).count(), 1);
        let text = ctxrace_config::validate::Causes(&err).to_string();
        for needle in [
            "continue the run with an empty replay",
            "replay.snapshot.damaged",
            "restoring replay snapshot",
            "shorter than a snapshot header",
        ] {
            assert!(text.contains(needle), "no '{needle}' in: {text}");
        }
        assert_eq!(
            text.matches("restoring replay snapshot").count(),
            1,
            "{text}"
        );
    }
}
