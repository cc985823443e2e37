//! The learner process (`ctxrace learner`): trains on batches from the run's replay, publishes
//! the policy weights every `policy_every` gradient steps, logs every `log_every` and
//! checkpoints every `checkpoint_every` (and on SIGTERM/SIGINT). It smooths the returns of the
//! actors' finished episodes and saves the policy as the run's best checkpoint at each new peak
//! ([`crate::best`]). It resumes from the newest checkpoint of the run directory, so a restarted
//! learner carries on where it stopped.

use crate::best::{write_best, ReturnTracker};
use crate::checkpoint::{latest_checkpoint, write_checkpoint};
use crate::runlog::MetricsLog;
use anyhow::{Context as _, Result};
use ctxrace_common::ipc::{
    termination_flag, EpisodeSubscriber, ReplayClient, RunTransport, WeightsPublisher,
    DEFAULT_MAX_WEIGHTS_BYTES,
};
use ctxrace_common::policy::ACT_DIM;
use ctxrace_common::ExperimentConfig;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// How long the learner waits for the replay to come up.
const HANDSHAKE: Duration = Duration::from_secs(60);
/// How long one batch request waits before the learner checks for signals again.
const BATCH_WAIT: Duration = Duration::from_millis(200);

/// What a learner process needs.
pub struct LearnerOptions {
    /// The run's iceoryx2 prefix.
    pub prefix: String,
    /// Actors in the run.
    pub actors: usize,
    /// The run directory (checkpoints, metrics).
    pub run_dir: PathBuf,
    /// The experiment.
    pub experiment: ExperimentConfig,
    /// Size of one observation frame.
    pub frame_dim: usize,
}

/// Gradient steps a run takes in all: `train_ratio` per env step after the prefill.
pub fn target_steps(cfg: &ExperimentConfig) -> u64 {
    cfg.gradient_steps()
}

/// Trains until the run's gradient-step target or SIGTERM/SIGINT; returns the steps taken.
pub fn run(opts: LearnerOptions) -> Result<u64> {
    let cfg = &opts.experiment;
    let t = &cfg.train;
    ctxrace_common::nn::candle_on_one_thread();
    let workers = t.threads_for(cfg.agent.algo);
    let mut algo = crate::build(&cfg.agent, opts.frame_dim, workers)?;
    let mut tracker = ReturnTracker::default();
    if let Some(ckpt) = latest_checkpoint(&opts.run_dir) {
        algo.load(&ckpt)
            .with_context(|| format!("resuming from {}", ckpt.display()))?;
        tracker = ReturnTracker::load(&ckpt)?;
        tracing::info!(
            "learner resumed from {} at step {}",
            ckpt.display(),
            algo.steps()
        );
    }
    let transport = RunTransport::open(&opts.prefix, opts.actors, "learner")?;
    let weights = WeightsPublisher::new(&transport, DEFAULT_MAX_WEIGHTS_BYTES)?;
    weights.publish(algo.steps(), &algo.policy_weights()?)?;
    let mut replay = ReplayClient::new(&transport, opts.frame_dim, ACT_DIM, HANDSHAKE)?;
    let mut episodes = EpisodeSubscriber::new(&transport)?;
    let mut log = MetricsLog::open(&opts.run_dir, "learner")?;
    let spec = cfg.agent.batch_spec();
    let target = target_steps(cfg);
    let start = Instant::now();
    let first = algo.steps();
    let stop = termination_flag()?;
    while algo.steps() < target && !stop.load(Ordering::Relaxed) {
        // late or restarted actors get the newest weights only when the publisher acts
        weights.update_connections()?;
        let mut new_best = false;
        for e in episodes.episodes()? {
            // every episode moves the smoothed return, so no short-circuit here
            if e.by_policy == 1 {
                new_best |= tracker.observe(e.episode_return as f64);
            }
        }
        if new_best {
            write_best(&opts.run_dir, algo.as_ref(), &cfg.agent, &tracker)?;
        }
        let Some(batch) = replay.next_batch(spec, BATCH_WAIT)? else {
            continue;
        };
        let mut m = algo.train_step(&batch)?;
        let steps = algo.steps();
        if steps.is_multiple_of(t.policy_every) {
            weights.publish(steps, &algo.policy_weights()?)?;
        }
        if steps.is_multiple_of(t.log_every) {
            m.insert("grad_steps".into(), steps as f64);
            m.insert("seconds".into(), start.elapsed().as_secs_f64());
            m.insert(
                "grad_steps_per_second".into(),
                (steps - first) as f64 / start.elapsed().as_secs_f64(),
            );
            log.write(&m)?;
        }
        if t.checkpoint_every > 0 && steps.is_multiple_of(t.checkpoint_every) {
            write_checkpoint(&opts.run_dir, algo.as_ref(), &cfg.agent, &tracker)?;
        }
    }
    weights.publish(algo.steps(), &algo.policy_weights()?)?;
    let last = write_checkpoint(&opts.run_dir, algo.as_ref(), &cfg.agent, &tracker)?;
    tracing::info!(
        "learner stopping at step {}: {}",
        algo.steps(),
        last.display()
    );
    Ok(algo.steps())
}
