//! What a training loop does around its gradient steps, written once for the learner process
//! ([`crate::process`]) and the single-process trainer ([`crate::inline`]): the smoothed return
//! of the policy's finished episodes and the best checkpoint at each new peak
//! ([`crate::best`]); after each gradient step a metrics row every `log_every` steps, a
//! checkpoint every `checkpoint_every` and the policy's publication due every `policy_every`;
//! the last checkpoint at the end.

use crate::best::{keep_best_at, write_best, ReturnTracker};
use crate::checkpoint::{write_checkpoint, CheckpointError};
use crate::runlog::{LogError, MetricsLog};
use crate::{Algorithm, Metrics};
use ctxrace_config::{AgentConfig, ExperimentConfig, TrainConfig};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Why the cadence could not log or checkpoint.
#[derive(Debug, thiserror::Error)]
pub enum CadenceError {
    /// A checkpoint or the best policy could not be written.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The metrics log could not be opened or written.
    #[error(transparent)]
    Log(#[from] LogError),
}

/// The outcome of a cadence operation.
type Result<T> = std::result::Result<T, CadenceError>;

/// A run's logging, checkpoint and best-policy cadence.
pub struct Cadence {
    run_dir: PathBuf,
    agent: AgentConfig,
    train: TrainConfig,
    tracker: ReturnTracker,
    log: MetricsLog,
    start: Instant,
    rate_since: Option<u64>,
}

impl Cadence {
    /// Opens (appending) the metrics log of `run_dir` with a new event file for the process
    /// `role`; `tracker` carries the smoothed return on (a resumed run's, else the default).
    /// The rows' `seconds` count from now.
    pub fn open(
        run_dir: &Path,
        cfg: &ExperimentConfig,
        role: &str,
        tracker: ReturnTracker,
    ) -> Result<Self> {
        Ok(Self {
            run_dir: run_dir.to_path_buf(),
            agent: cfg.agent.clone(),
            train: cfg.train.clone(),
            tracker,
            log: MetricsLog::open(run_dir, role)?,
            start: Instant::now(),
            rate_since: None,
        })
    }

    /// Adds to every metrics row `grad_steps_per_second`, the rate since gradient step `first`
    /// (where this process started).
    pub fn with_rate_since(mut self, first: u64) -> Self {
        self.rate_since = Some(first);
        self
    }

    /// The smoothed return behind the best checkpoint.
    pub fn tracker(&self) -> &ReturnTracker {
        &self.tracker
    }

    /// Moves the smoothed return by the returns of the policy's finished episodes (every one
    /// moves it); saves `algo`'s policy as the run's best if it reached a new peak.
    pub fn observe_returns(
        &mut self,
        algo: &dyn Algorithm,
        returns: impl IntoIterator<Item = f64>,
    ) -> Result<()> {
        let mut new_best = false;
        for episode_return in returns {
            new_best |= self.tracker.observe(episode_return);
        }
        if new_best {
            write_best(&self.run_dir, algo, &self.agent, &self.tracker)?;
        }
        Ok(())
    }

    /// Keeps a copy of the best policy if the run has taken one of `[train] keep_best_at`'s
    /// env-step counts (called after each decision with the run's count).
    pub fn env_steps_taken(&self, env_steps: u64) -> Result<()> {
        if self.train.keep_best_at.contains(&env_steps) {
            keep_best_at(&self.run_dir, env_steps)?;
        }
        Ok(())
    }

    /// After a gradient step of `algo` that reported `metrics`: logs them (with `grad_steps`,
    /// `seconds` and, where the caller knows them, the run's `env_steps`) and checkpoints when
    /// due. Returns whether the policy's publication is due.
    pub fn after_step(
        &mut self,
        algo: &dyn Algorithm,
        mut metrics: Metrics,
        env_steps: Option<u64>,
    ) -> Result<bool> {
        let steps = algo.steps();
        let t = &self.train;
        if steps.is_multiple_of(t.log_every) {
            let seconds = self.start.elapsed().as_secs_f64();
            metrics.insert("grad_steps".into(), steps as f64);
            if let Some(env_steps) = env_steps {
                metrics.insert("env_steps".into(), env_steps as f64);
            }
            metrics.insert("seconds".into(), seconds);
            if let Some(first) = self.rate_since {
                let rate = (steps - first) as f64 / seconds;
                metrics.insert("grad_steps_per_second".into(), rate);
            }
            self.log.write(&metrics)?;
        }
        if t.checkpoint_every > 0 && steps.is_multiple_of(t.checkpoint_every) {
            write_checkpoint(&self.run_dir, algo, &self.agent, &self.tracker)?;
        }
        Ok(steps.is_multiple_of(t.policy_every))
    }

    /// Writes the last checkpoint of `algo`; returns its path.
    pub fn finish(self, algo: &dyn Algorithm) -> Result<PathBuf> {
        Ok(write_checkpoint(
            &self.run_dir,
            algo,
            &self.agent,
            &self.tracker,
        )?)
    }
}
