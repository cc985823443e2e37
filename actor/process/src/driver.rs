//! Who drives the ego in an evaluation episode: a reference policy of the simulator or a
//! trained agent's acting policy, sampling its distributions or taking their modes.

use ctxrace_config::AgentConfig;
use ctxrace_nn::policy::PolicyError;
use ctxrace_nn::Policy;
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::{ActMode, BaselineEgo, Ego, EgoAction};
use ctxrace_sim::RaceEnv;

/// An ego driver with its per-episode state.
pub enum Driver {
    /// A reference policy.
    Baseline(BaselineEgo),
    /// A trained agent, sampling or taking the mode of its distributions.
    Agent(Box<Policy>, ActMode),
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
        let policy = Policy::new(agent, env.obs_dim(), weights, 0)?;
        Ok(Driver::Agent(Box::new(policy), act))
    }
}

impl Ego for Driver {
    type Error = PolicyError;

    fn reset(&mut self, env: &RaceEnv, seed: u64) {
        match self {
            Driver::Baseline(b) => b.reset(env, seed),
            Driver::Agent(p, _) => {
                p.reset();
                p.reseed(seed);
            }
        }
    }

    fn act(&mut self, env: &RaceEnv, obs: &[f32]) -> Result<EgoAction, PolicyError> {
        Ok(match self {
            Driver::Baseline(b) => {
                let Ok(decision) = b.act(env, obs);
                decision
            }
            Driver::Agent(p, act) => {
                let c = env.context();
                let mode = *act == ActMode::Mode;
                let d = p.act(obs, [c.speed as f32, c.steer as f32], mode)?;
                (d.action.map(f64::from), d.mask)
            }
        })
    }
}
