//! Who drives the ego in an evaluation episode: a reference policy or a trained agent's acting
//! policy, sampling its distributions or taking their modes; and the episode loop that drives
//! it (reset, decisions, the end), showing every decision to an observer.

use crate::baseline::{Baseline, BaselineKind};
use crate::race::{RaceEnv, StepInfo};
use anyhow::Result;
use ctxrace_common::{AgentConfig, Context, Policy};
use serde::{Deserialize, Serialize};

/// How a trained agent picks its actions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum ActMode {
    /// Samples its action (and cMask its mask) distribution, seeded per episode: the paper's
    /// evaluation.
    Sample,
    /// Takes the mode of each distribution.
    Mode,
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
    /// A reference policy driving `env`'s ego.
    pub fn baseline(kind: BaselineKind, env: &RaceEnv) -> Self {
        Driver::Baseline(kind, Baseline::new(kind, env, 0))
    }

    /// A trained agent (its configuration and policy weights, safetensors bytes) driving
    /// `env`'s ego, acting by `act`.
    pub fn agent(agent: &AgentConfig, weights: &[u8], env: &RaceEnv, act: ActMode) -> Result<Self> {
        let policy = Policy::new(agent, env.obs_dim(), weights, 0)?;
        Ok(Driver::Agent(Box::new(policy), act))
    }

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

    /// Runs one episode of `env` under `context` from `seed` to its end; returns the last
    /// step's details.
    pub fn drive_episode(
        &mut self,
        env: &mut RaceEnv,
        context: Context,
        seed: u64,
    ) -> Result<StepInfo> {
        self.drive_observed(env, context, seed, |_, _| {})
    }

    /// Runs one episode like [`Driver::drive_episode`], showing `observe` the environment after
    /// its reset (a [`Decided`] with no action, mask or reward) and after every decision.
    pub fn drive_observed(
        &mut self,
        env: &mut RaceEnv,
        context: Context,
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
