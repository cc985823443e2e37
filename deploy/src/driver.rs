//! Who drives the ego: a reference policy or a trained agent loaded from a checkpoint.

use crate::render::Frame;
use anyhow::{bail, Context as _, Result};
use ctxrace_actor::baseline::{Baseline, BaselineKind};
use ctxrace_actor::{RaceEnv, StepInfo};
use ctxrace_common::{AgentConfig, ExperimentConfig, Policy};
use ctxrace_learner::checkpoint::{latest_checkpoint, AGENT_FILE, POLICY_FILE};
use std::path::{Path, PathBuf};

/// A trained agent's acting side as stored in a checkpoint.
#[derive(Clone, Debug)]
pub struct TrainedAgent {
    /// The checkpoint directory.
    pub checkpoint: PathBuf,
    /// The agent's configuration.
    pub agent: AgentConfig,
    /// The policy weights (safetensors bytes).
    pub weights: Vec<u8>,
    /// The experiment of the run it belongs to, when the run directory is known.
    pub experiment: Option<ExperimentConfig>,
}

impl TrainedAgent {
    /// Loads a checkpoint directory, or the newest checkpoint of a run directory.
    pub fn load(path: &Path) -> Result<Self> {
        let (checkpoint, run_dir) = if path.join(POLICY_FILE).exists() {
            let run = path.parent().and_then(Path::parent).map(Path::to_path_buf);
            (path.to_path_buf(), run)
        } else if let Some(latest) = latest_checkpoint(path) {
            (latest, Some(path.to_path_buf()))
        } else {
            bail!(
                "{} is neither a checkpoint (no {POLICY_FILE}) nor a run directory with \
                 checkpoints/step-*; train one with `ctxrace train`",
                path.display()
            );
        };
        let agent_path = checkpoint.join(AGENT_FILE);
        let text = std::fs::read_to_string(&agent_path)
            .with_context(|| format!("reading {}", agent_path.display()))?;
        let agent: AgentConfig =
            toml::from_str(&text).with_context(|| format!("parsing {}", agent_path.display()))?;
        let policy_path = checkpoint.join(POLICY_FILE);
        let weights = std::fs::read(&policy_path)
            .with_context(|| format!("reading {}", policy_path.display()))?;
        let experiment = match run_dir.map(|r| r.join(crate::train::CONFIG_FILE)) {
            Some(p) if p.exists() => Some(ExperimentConfig::load(&p).map_err(anyhow::Error::msg)?),
            _ => None,
        };
        Ok(Self {
            checkpoint,
            agent,
            weights,
            experiment,
        })
    }
}

/// What drives the ego.
#[derive(Clone, Debug)]
pub enum EgoSpec {
    /// A reference policy.
    Baseline(BaselineKind),
    /// A trained agent.
    Trained(Box<TrainedAgent>),
}

impl EgoSpec {
    /// The name reports group by: the algorithm or the baseline.
    pub fn name(&self) -> String {
        match self {
            EgoSpec::Baseline(BaselineKind::PurePursuit) => "pure-pursuit".into(),
            EgoSpec::Baseline(BaselineKind::Random) => "random".into(),
            EgoSpec::Baseline(BaselineKind::Still) => "still".into(),
            EgoSpec::Trained(t) => t.agent.algo.name().into(),
        }
    }

    /// A driver for `env`'s episodes.
    pub fn driver(&self, env: &RaceEnv) -> Result<Driver> {
        Ok(match self {
            EgoSpec::Baseline(kind) => Driver::Baseline(*kind, Baseline::new(*kind, env, 0)),
            EgoSpec::Trained(t) => Driver::Agent(Box::new(
                Policy::new(&t.agent, env.obs_dim(), &t.weights, 0).with_context(|| {
                    format!(
                        "the checkpoint {} does not fit this race's observations ({} values)",
                        t.checkpoint.display(),
                        env.obs_dim()
                    )
                })?,
            )),
        })
    }
}

/// An ego driver with its per-episode state.
pub enum Driver {
    /// A reference policy.
    Baseline(BaselineKind, Baseline),
    /// A trained agent, acting deterministically (the mode of its distribution).
    Agent(Box<Policy>),
}

impl Driver {
    /// Starts an episode of `env` (after its reset); `seed` drives the random baseline.
    pub fn reset(&mut self, env: &RaceEnv, seed: u64) {
        match self {
            Driver::Baseline(kind, b) => *b = Baseline::new(*kind, env, seed),
            Driver::Agent(p) => p.reset(),
        }
    }

    /// Runs one episode of `env` under `context` from `seed` to its end, recording a frame per
    /// decision into `frames` if given; returns the last step's details.
    pub fn drive_episode(
        &mut self,
        env: &mut RaceEnv,
        context: ctxrace_common::Context,
        seed: u64,
        mut frames: Option<&mut Vec<Frame>>,
    ) -> Result<StepInfo> {
        let mut obs = env.reset(seed, context);
        self.reset(env, seed);
        if let Some(f) = frames.as_deref_mut() {
            f.push(Frame::capture(env, [0.0, 0.0], 0.0, &obs));
        }
        loop {
            let (action, _) = self.act(env, &obs)?;
            let step = env.step(action)?;
            obs = step.obs;
            if let Some(f) = frames.as_deref_mut() {
                f.push(Frame::capture(env, action, step.reward, &obs));
            }
            if step.terminated || step.truncated {
                return Ok(step.info);
            }
        }
    }

    /// The action for observation `obs` of `env`, and (cMask) the context mask used.
    pub fn act(&mut self, env: &RaceEnv, obs: &[f32]) -> Result<([f64; 2], Option<[f32; 2]>)> {
        Ok(match self {
            Driver::Baseline(_, b) => (b.act(env), None),
            Driver::Agent(p) => {
                let c = env.context();
                let d = p.act(obs, [c.speed as f32, c.steer as f32], true)?;
                (d.action.map(f64::from), d.mask)
            }
        })
    }
}
