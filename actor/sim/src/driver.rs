//! Who drives the ego in an episode ([`Ego`]: a reference policy here, a trained agent's acting
//! policy in the actor crate, a Python agent in the bindings), how a trained agent acts
//! ([`ActMode`]), and the episode loop that drives it (reset, decisions, the end), showing every
//! decision to an observer.

use crate::baseline::{Baseline, BaselineKind};
use crate::race::{RaceEnv, RaceError, StepInfo};
use ctxrace_config::Context;
use serde::{Deserialize, Serialize};

/// How a trained agent picks its actions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum ActMode {
    /// Samples its action (and cMask its mask) distribution, seeded per episode: the paper's
    /// evaluation, and the default.
    #[default]
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

/// An ego's decision: the action and (cMask) the context mask that chose it.
pub type EgoAction = ([f64; 2], Option<[f32; 2]>);

/// Why an episode could not be driven to its end: the ego could not act (its own error type,
/// [`Ego::Error`]), or the race refused its action.
#[derive(Debug, thiserror::Error)]
pub enum DriveError<E> {
    /// The ego could not pick an action.
    #[error(transparent)]
    Ego(E),
    /// The race refused the action (not finite) or the step.
    #[error(transparent)]
    Race(#[from] RaceError),
}

/// An ego driver with its per-episode state: it picks the ego's action from the race's
/// observation.
pub trait Ego {
    /// Why it could not act ([`std::convert::Infallible`] for a reference policy, the policy's
    /// error for a trained agent).
    type Error: std::error::Error + Send + Sync + 'static;

    /// Starts an episode of `env` (after its reset); `seed` drives its randomness (the random
    /// baseline, a sampling agent's noise).
    fn reset(&mut self, env: &RaceEnv, seed: u64);

    /// The action for observation `obs` of `env`, and (cMask) the context mask used.
    fn act(&mut self, env: &RaceEnv, obs: &[f32]) -> Result<EgoAction, Self::Error>;

    /// Runs one episode of `env` under `context` from `seed` to its end; returns the last
    /// step's details.
    fn drive_episode(
        &mut self,
        env: &mut RaceEnv,
        context: Context,
        seed: u64,
    ) -> Result<StepInfo, DriveError<Self::Error>>
    where
        Self: Sized,
    {
        self.drive_observed(env, context, seed, |_, _| {})
    }

    /// Runs one episode like [`Ego::drive_episode`], showing `observe` the environment after
    /// its reset (a [`Decided`] with no action, mask or reward) and after every decision.
    fn drive_observed(
        &mut self,
        env: &mut RaceEnv,
        context: Context,
        seed: u64,
        mut observe: impl FnMut(&RaceEnv, Decided),
    ) -> Result<StepInfo, DriveError<Self::Error>>
    where
        Self: Sized,
    {
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
            let (action, mask) = self.act(env, &obs).map_err(DriveError::Ego)?;
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
}

/// A reference policy driving the ego ([`BaselineKind`]), fresh each episode.
pub struct BaselineEgo {
    kind: BaselineKind,
    state: Baseline,
}

impl BaselineEgo {
    /// The reference policy `kind` driving `env`'s ego.
    pub fn new(kind: BaselineKind, env: &RaceEnv) -> Self {
        Self {
            kind,
            state: Baseline::new(kind, env, 0),
        }
    }
}

impl Ego for BaselineEgo {
    type Error = std::convert::Infallible;

    fn reset(&mut self, env: &RaceEnv, seed: u64) {
        self.state = Baseline::new(self.kind, env, seed);
    }

    fn act(&mut self, env: &RaceEnv, _obs: &[f32]) -> Result<EgoAction, Self::Error> {
        Ok((self.state.act(env), None))
    }
}
