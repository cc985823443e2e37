//! Who drives the ego in an evaluation episode: a reference policy of the simulator or a
//! trained agent's acting policy, sampling its distributions or taking their modes, told the
//! episode's context or (the context ablation) another one.

use ctxrace_config::{AgentConfig, Context};
use ctxrace_nn::policy::PolicyError;
use ctxrace_nn::Policy;
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::{ActMode, BaselineEgo, Ego, EgoAction};
use ctxrace_sim::RaceEnv;

/// An ego driver with its per-episode state.
pub enum Driver {
    /// A reference policy.
    Baseline(BaselineEgo),
    /// A trained agent.
    Agent(Box<AgentEgo>),
}

/// A trained agent driving the ego.
pub struct AgentEgo {
    /// Its acting policy.
    policy: Policy,
    /// Sampling or taking the mode of its distributions.
    act: ActMode,
    /// The context it is told instead of the race's (`None`: the truth).
    told: Option<Context>,
}

impl Driver {
    /// A reference policy driving `env`'s ego.
    pub fn baseline(kind: BaselineKind, env: &RaceEnv) -> Self {
        Driver::Baseline(BaselineEgo::new(kind, env))
    }

    /// A trained agent (its configuration and policy weights, safetensors bytes) driving
    /// `env`'s ego, acting by `act`.
    pub fn agent(
        agent: &AgentConfig,
        weights: &[u8],
        env: &RaceEnv,
        act: ActMode,
    ) -> Result<Self, PolicyError> {
        Ok(Self::policy(
            Policy::new(agent, env.obs_dim(), weights, 0)?,
            act,
        ))
    }

    /// Any acting `policy` driving the ego (a policy trained elsewhere: [`Policy::mlp`]), acting
    /// by `act`.
    pub fn policy(policy: Policy, act: ActMode) -> Self {
        Driver::Agent(Box::new(AgentEgo {
            policy,
            act,
            told: None,
        }))
    }

    /// Tells a trained agent `context` instead of the race's from now on (`None`: the truth);
    /// the rivals keep driving by the race's. A reference policy reads no context.
    pub fn tell(&mut self, context: Option<Context>) {
        if let Driver::Agent(a) = self {
            a.told = context;
        }
    }

    /// Fixes a cMask agent's mask (`None`: chosen again); an error for any other driver.
    pub fn fix_mask(&mut self, mask: Option<[f32; 2]>) -> Result<(), PolicyError> {
        match self {
            Driver::Agent(a) => a.policy.fix_mask(mask),
            Driver::Baseline(_) if mask.is_none() => Ok(()),
            Driver::Baseline(_) => Err(PolicyError::NoMask),
        }
    }
}

impl Ego for Driver {
    type Error = PolicyError;

    fn reset(&mut self, env: &RaceEnv, seed: u64) {
        match self {
            Driver::Baseline(b) => b.reset(env, seed),
            Driver::Agent(a) => {
                a.policy.reset();
                a.policy.reseed(seed);
            }
        }
    }

    fn act(&mut self, env: &RaceEnv, obs: &[f32]) -> Result<EgoAction, PolicyError> {
        Ok(match self {
            Driver::Baseline(b) => {
                let Ok(decision) = b.act(env, obs);
                decision
            }
            Driver::Agent(a) => {
                let c = a.told.unwrap_or_else(|| env.context());
                let mode = a.act == ActMode::Mode;
                let d = a.policy.act(obs, [c.speed as f32, c.steer as f32], mode)?;
                (d.action.map(f64::from), d.mask)
            }
        })
    }
}
