//! The learner process (`ctxrace learner`): trains on batches from the run's replay, publishes
//! the policy weights every `policy_every` gradient steps, logs every `log_every` and
//! checkpoints every `checkpoint_every` (and on SIGTERM/SIGINT). It smooths the returns of the
//! actors' finished episodes and saves the policy as the run's best checkpoint at each new peak
//! ([`crate::best`]); the cadence is [`crate::cadence`]'s, as the single-process trainer's. It resumes from the newest checkpoint of the run directory, so a restarted
//! learner carries on where it stopped.

use crate::best::ReturnTracker;
use crate::cadence::{Cadence, CadenceError};
use crate::checkpoint::{checkpoint_step, latest_checkpoint, CheckpointError};
use crate::LearnerError;
use ctxrace_config::ExperimentConfig;
use ctxrace_ipc::wire::named_reasons;
use ctxrace_ipc::{
    termination_flag, EpisodeSubscriber, IpcError, ReplayClient, RunBounds, RunTransport,
    WeightsPublisher, DEFAULT_MAX_WEIGHTS_BYTES,
};
use ctxrace_nn::policy::ACT_DIM;
use ctxrace_run::results::{write_json, ResultsError};
use ctxrace_run::run_dir::LEARNER_STATUS;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// How long the learner waits for the replay to come up.
const HANDSHAKE: Duration = Duration::from_secs(60);
/// How long one batch request waits before the learner checks for signals again.
const BATCH_WAIT: Duration = Duration::from_millis(200);
/// How often the learner rewrites its status file ([`LEARNER_STATUS`]).
const STATUS_EVERY: Duration = Duration::from_secs(1);

/// Why the learner process stopped on an error.
#[derive(Debug, thiserror::Error)]
pub enum ProcessError {
    /// The agent could not be built, or a training step failed.
    #[error(transparent)]
    Learner(#[from] LearnerError),
    /// The run's newest checkpoint could not be restored.
    #[error("resuming from {}", .path.display())]
    Resume {
        /// The checkpoint.
        path: PathBuf,
        /// Why.
        #[source]
        source: CheckpointError,
    },
    /// The logs, a checkpoint or the best policy could not be written.
    #[error(transparent)]
    Cadence(#[from] CadenceError),
    /// The transport failed.
    #[error(transparent)]
    Ipc(#[from] IpcError),
    /// The status file could not be written.
    #[error(transparent)]
    Status(#[from] ResultsError),
}

/// Writes the transport counters of this learner start, which began at gradient step
/// `started_at` ([`LEARNER_STATUS`]): batches trained on, requests sent again unanswered,
/// request publishers renewed, requests refused by the replay and answers rejected (by reason),
/// episode reports rejected.
fn write_status(
    run_dir: &Path,
    started_at: u64,
    grad_steps: u64,
    batches: u64,
    replay: &ReplayClient,
    episodes: &EpisodeSubscriber,
) -> Result<(), ResultsError> {
    let status = serde_json::json!({
        "started_at_grad_step": started_at,
        "grad_steps": grad_steps,
        "batches": batches,
        "batch_requests_resent": replay.resent(),
        "request_publishers_renewed": replay.publishers_renewed(),
        "refused_by_replay": named_reasons(&replay.refused_by_reason()),
        "answers_rejected": named_reasons(&replay.rejected_by_reason()),
        "episode_reports_rejected": named_reasons(&episodes.rejected_by_reason()),
    });
    write_json(&run_dir.join(LEARNER_STATUS), &status)
}

/// What a learner process needs.
pub struct LearnerOptions {
    /// The run's iceoryx2 prefix.
    pub prefix: String,
    /// The run's key, which seals and checks every message.
    pub key: ctxrace_ipc::RunKey,
    /// Actors in the run.
    pub actors: usize,
    /// The run directory (checkpoints, metrics).
    pub run_dir: PathBuf,
    /// The experiment.
    pub experiment: ExperimentConfig,
    /// Size of one observation frame.
    pub frame_dim: usize,
}

/// Whether the run in `dir` has taken all its gradient steps (its newest checkpoint is the
/// learner's last).
pub fn is_trained(dir: &Path, cfg: &ExperimentConfig) -> bool {
    resume_step(dir) >= cfg.plan().gradient_steps
}

/// The gradient step of the newest intact checkpoint of the run in `dir`, where a (re)started
/// learner resumes (0 without one).
pub fn resume_step(dir: &Path) -> u64 {
    latest_checkpoint(dir)
        .and_then(|c| checkpoint_step(&c))
        .unwrap_or(0)
}

/// Trains until the run's gradient-step target or SIGTERM/SIGINT; returns the steps taken.
pub fn run(opts: LearnerOptions) -> Result<u64, ProcessError> {
    let cfg = &opts.experiment;
    let t = &cfg.train;
    let workers = t.threads_for(cfg.agent.algo);
    let mut algo = crate::build(&cfg.agent, opts.frame_dim, workers)?;
    algo.set_diagnostics_every(t.log_every);
    let mut tracker = ReturnTracker::default();
    if let Some(ckpt) = latest_checkpoint(&opts.run_dir) {
        let resume = |source| ProcessError::Resume {
            path: ckpt.clone(),
            source,
        };
        algo.load(&ckpt).map_err(resume)?;
        tracker = ReturnTracker::load(&ckpt).map_err(resume)?;
        tracing::info!(
            "learner resumed from {} at step {}",
            ckpt.display(),
            algo.steps()
        );
    }
    let transport = RunTransport::open(&opts.prefix, opts.actors, "learner", &opts.key)?;
    let weights = WeightsPublisher::new(&transport, DEFAULT_MAX_WEIGHTS_BYTES)?;
    weights.publish(algo.steps(), &algo.policy_weights()?)?;
    let mut replay = ReplayClient::new(&transport, opts.frame_dim, ACT_DIM, HANDSHAKE)?;
    let mut episodes = EpisodeSubscriber::new(&transport, RunBounds::of(cfg, opts.actors))?;
    let first = algo.steps();
    let mut cadence = Cadence::open(&opts.run_dir, cfg, "learner", tracker)?.with_rate_since(first);
    let spec = cfg.agent.batch_spec();
    let target = cfg.plan().gradient_steps;
    let stop = termination_flag()?;
    let mut batches = 0u64;
    let mut last_status = Instant::now();
    while algo.steps() < target && !stop.load(Ordering::Relaxed) {
        if last_status.elapsed() >= STATUS_EVERY {
            write_status(
                &opts.run_dir,
                first,
                algo.steps(),
                batches,
                &replay,
                &episodes,
            )?;
            last_status = Instant::now();
        }
        // late or restarted actors get the newest weights only when the publisher acts
        weights.update_connections()?;
        let policy_returns = episodes
            .episodes()?
            .into_iter()
            .filter(|e| e.by_policy == 1)
            .map(|e| e.episode_return as f64);
        cadence.observe_returns(algo.as_ref(), policy_returns)?;
        let Some(batch) = replay.next_batch(spec, BATCH_WAIT)? else {
            continue;
        };
        batches += 1;
        let metrics = algo.train_step(&batch)?;
        if cadence.after_step(algo.as_ref(), metrics, None)? {
            weights.publish(algo.steps(), &algo.policy_weights()?)?;
        }
    }
    weights.publish(algo.steps(), &algo.policy_weights()?)?;
    write_status(
        &opts.run_dir,
        first,
        algo.steps(),
        batches,
        &replay,
        &episodes,
    )?;
    let refused = named_reasons(&replay.refused_by_reason());
    if replay.resent() > 0 || !refused.is_empty() || replay.rejected() > 0 {
        tracing::warn!(
            "batch requests: {} sent again unanswered, refused by the replay {refused:?}, {} \
             answers rejected",
            replay.resent(),
            replay.rejected()
        );
    }
    let last = cadence.finish(algo.as_ref())?;
    tracing::info!(
        "learner stopping at step {}: {}",
        algo.steps(),
        last.display()
    );
    Ok(algo.steps())
}
