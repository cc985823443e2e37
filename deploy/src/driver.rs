//! Who drives the ego: a reference policy or a trained agent loaded from a checkpoint
//! (`ctxrace_learner::trained`).

use crate::render::Frame;
use anyhow::{Context as _, Result};
use ctxrace_actor::baseline::{Baseline, BaselineKind};
use ctxrace_actor::{RaceEnv, StepInfo};
use ctxrace_common::Policy;
use ctxrace_learner::trained::TrainedAgent;
use serde::{Deserialize, Serialize};

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

/// One decision of an episode, as [`Driver::drive_observed`] shows it.
#[derive(Clone, Copy, Debug)]
pub struct Decided<'a> {
    /// The ego action taken.
    pub action: [f64; 2],
    /// cMask's context mask that chose it.
    pub mask: Option<[f32; 2]>,
    /// The reward it earned.
    pub reward: f64,
    /// The observation after it.
    pub obs: &'a [f32],
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
        self.drive_observed(env, context, seed, |env, d| {
            if let Some(f) = frames.as_deref_mut() {
                f.push(Frame::capture(env, d.action, d.reward, d.obs));
            }
        })
    }

    /// Runs one episode like [`Driver::drive_episode`], showing `observe` the environment after
    /// its reset (a [`Decided`] with no action, mask or reward) and after every decision.
    pub fn drive_observed(
        &mut self,
        env: &mut RaceEnv,
        context: ctxrace_common::Context,
        seed: u64,
        mut observe: impl FnMut(&RaceEnv, Decided),
    ) -> Result<StepInfo> {
        let mut obs = env.reset(seed, context);
        self.reset(env, seed);
        let start = Decided {
            action: [0.0, 0.0],
            mask: None,
            reward: 0.0,
            obs: &obs,
        };
        observe(env, start);
        loop {
            let (action, mask) = self.act(env, &obs)?;
            let step = env.step(action)?;
            obs = step.obs;
            let decided = Decided {
                action,
                mask,
                reward: step.reward,
                obs: &obs,
            };
            observe(env, decided);
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
