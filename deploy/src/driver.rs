//! Who drives the ego: a reference policy or a trained agent loaded from a checkpoint.

use crate::render::Frame;
use anyhow::{bail, Context as _, Result};
use ctxrace_actor::baseline::{Baseline, BaselineKind};
use ctxrace_actor::{RaceEnv, StepInfo};
use ctxrace_common::run_dir::{AGENT_FILE, CONFIG_FILE, POLICY_FILE};
use ctxrace_common::{AgentConfig, ExperimentConfig, Policy};
use ctxrace_learner::best::best_checkpoint;
use ctxrace_learner::checkpoint::{checkpoints, latest_checkpoint};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Which checkpoint of a run directory to load.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckpointChoice {
    /// The policy at the peak of the smoothed training return (the paper's `best_`).
    Best,
    /// The newest checkpoint.
    Latest,
    /// The checkpoint after this many gradient steps.
    Step(u64),
}

impl std::str::FromStr for CheckpointChoice {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "best" => Ok(Self::Best),
            "latest" => Ok(Self::Latest),
            _ => s
                .strip_prefix("step-")
                .and_then(|n| n.parse().ok())
                .map(Self::Step)
                .ok_or_else(|| format!("'{s}' is not best, latest or step-N (e.g. step-5000)")),
        }
    }
}

impl std::fmt::Display for CheckpointChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Best => write!(f, "best"),
            Self::Latest => write!(f, "latest"),
            Self::Step(n) => write!(f, "step-{n}"),
        }
    }
}

/// How a trained agent picks its actions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ActMode {
    /// Samples its action (and cMask its mask) distribution, seeded per episode: the paper's
    /// evaluation.
    Sample,
    /// Takes the mode of each distribution.
    Mode,
}

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
    /// Loads a checkpoint directory, or the checkpoint `choice` of a run directory.
    pub fn load(path: &Path, choice: CheckpointChoice) -> Result<Self> {
        let (checkpoint, run_dir) = if path.join(POLICY_FILE).exists() {
            let run = path.parent().and_then(Path::parent).map(Path::to_path_buf);
            (path.to_path_buf(), run)
        } else if latest_checkpoint(path).is_some() {
            (pick_checkpoint(path, choice)?, Some(path.to_path_buf()))
        } else {
            bail!(
                "{} is neither a checkpoint (no {POLICY_FILE}) nor a run directory with \
                 checkpoints/step-*; train one with `ctxrace train`",
                path.display()
            );
        };
        ctxrace_learner::checkpoint::verify(&checkpoint)?;
        let agent_path = checkpoint.join(AGENT_FILE);
        let text = std::fs::read_to_string(&agent_path)
            .with_context(|| format!("reading {}", agent_path.display()))?;
        let agent: AgentConfig =
            toml::from_str(&text).with_context(|| format!("parsing {}", agent_path.display()))?;
        let policy_path = checkpoint.join(POLICY_FILE);
        let weights = std::fs::read(&policy_path)
            .with_context(|| format!("reading {}", policy_path.display()))?;
        let experiment = match run_dir.map(|r| r.join(CONFIG_FILE)) {
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

/// The checkpoint `choice` of the run directory `run`, or an error saying which there are.
fn pick_checkpoint(run: &Path, choice: CheckpointChoice) -> Result<PathBuf> {
    let found = match choice {
        CheckpointChoice::Best => best_checkpoint(run),
        CheckpointChoice::Latest => latest_checkpoint(run),
        CheckpointChoice::Step(n) => checkpoints(run)
            .into_iter()
            .find(|c| c.file_name() == Some(std::ffi::OsStr::new(&format!("step-{n:010}")))),
    };
    found.ok_or_else(|| {
        let steps: Vec<String> = checkpoints(run)
            .iter()
            .filter_map(|c| {
                c.file_name()?
                    .to_str()?
                    .strip_prefix("step-")?
                    .parse::<u64>()
                    .ok()
            })
            .map(|n| format!("step-{n}"))
            .collect();
        let why = match choice {
            CheckpointChoice::Best => {
                " (the learner saves it when the policy drove a training episode; runs trained \
                 before ctxrace kept it have none)"
            }
            _ => "",
        };
        anyhow::anyhow!(
            "{} has no {choice} checkpoint{why}; pass --checkpoint latest or one of {}",
            run.display(),
            steps.join(", ")
        )
    })
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

    /// A driver for `env`'s episodes; a trained agent acts by `act`.
    pub fn driver(&self, env: &RaceEnv, act: ActMode) -> Result<Driver> {
        Ok(match self {
            EgoSpec::Baseline(kind) => Driver::Baseline(*kind, Baseline::new(*kind, env, 0)),
            EgoSpec::Trained(t) => Driver::Agent(
                Box::new(
                    Policy::new(&t.agent, env.obs_dim(), &t.weights, 0).with_context(|| {
                        format!(
                            "the checkpoint {} does not fit this race's observations ({} values)",
                            t.checkpoint.display(),
                            env.obs_dim()
                        )
                    })?,
                ),
                act,
            ),
        })
    }
}

/// An ego driver with its per-episode state.
pub enum Driver {
    /// A reference policy.
    Baseline(BaselineKind, Baseline),
    /// A trained agent, sampling or taking the mode of its distributions.
    Agent(Box<Policy>, ActMode),
}

impl Driver {
    /// Starts an episode of `env` (after its reset); `seed` drives the random baseline and a
    /// sampling agent's noise.
    pub fn reset(&mut self, env: &RaceEnv, seed: u64) {
        match self {
            Driver::Baseline(kind, b) => *b = Baseline::new(*kind, env, seed),
            Driver::Agent(p, _) => {
                p.reset();
                p.reseed(seed);
            }
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
            Driver::Agent(p, act) => {
                let c = env.context();
                let mode = *act == ActMode::Mode;
                let d = p.act(obs, [c.speed as f32, c.steer as f32], mode)?;
                (d.action.map(f64::from), d.mask)
            }
        })
    }
}
