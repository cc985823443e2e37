//! The policies the actors run at batch 1 on one thread: built from an [`AgentConfig`] and the
//! learner's policy weights (safetensors bytes), with their recurrent state or frame stack inside;
//! and policies trained elsewhere, as an MLP file ([`mlp`]).

mod dreamer;
pub mod mlp;
mod sac;

pub use dreamer::DreamerPolicy;
pub use mlp::MlpPolicy;
pub use sac::SacPolicy;

use crate::WeightsError;
use ctxrace_config::agents::{AgentConfig, AgentConfigError, AlgoKind};

/// Why a policy cannot be built from an agent configuration and policy weights, or cannot act
/// on an observation.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PolicyError {
    /// The agent configuration is not one a policy can be built from (its message names the key).
    #[error("the [agent] table cannot act: {0}")]
    Config(AgentConfigError),
    /// The weights are not a safetensors file of `f32` tensors, or are of another architecture
    /// than the agent configuration's.
    #[error(
        "the policy weights do not fit the [agent] table: {0}; act with the agent.toml of the \
         run that wrote them"
    )]
    Weights(WeightsError),
    /// An observation's size differs from the one the policy was built for.
    #[error(
        "an observation of {found} values reached a policy built for {want}; the [race] \
         lidar.beams must be the one the agent was trained with"
    )]
    Observation {
        /// Values in the observation.
        found: usize,
        /// Values the policy was built for.
        want: usize,
    },
    /// An MLP policy file ([`mlp`]) is not one, or cannot act in this race.
    #[error("not an MLP policy file that can act here: {0}")]
    Mlp(String),
    /// A mask was fixed for an agent that has none (only cMask masks its context).
    #[error("only a cMask agent has a context mask to fix")]
    NoMask,
}

// The causes are printed in the messages, not chained as sources, so that a `{:#}` chain (anyhow's)
// names each once.
impl From<AgentConfigError> for PolicyError {
    fn from(e: AgentConfigError) -> Self {
        Self::Config(e)
    }
}

impl From<WeightsError> for PolicyError {
    fn from(e: WeightsError) -> Self {
        Self::Weights(e)
    }
}

/// The outcome of building a policy or of one decision.
pub type Result<T> = std::result::Result<T, PolicyError>;

/// Action size of the racing policies: steering and speed.
pub const ACT_DIM: usize = 2;

/// One decision of a [`Policy`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Decision {
    /// The action in `[−1, 1]²` (steering, speed).
    pub action: [f32; 2],
    /// cMask's context mask `m ∈ [0, 1]²`, if the agent has one.
    pub mask: Option<[f32; 2]>,
}

/// What a policy carries from one episode into the next besides its weights: the position of
/// its sampling noise and, for SAC without `reset_frame_stack`, its frame stack (oldest first).
/// Taken at an episode boundary, it lets a resumed run act as the uninterrupted one would.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CarriedState {
    /// Words the sampling noise's stream has given (ChaCha's word position).
    pub rng_words: u128,
    /// SAC's frames kept for the next episode's stack (empty for Dreamer agents).
    pub frames: Vec<Vec<f32>>,
}

/// Any trained agent's acting side.
pub enum Policy {
    /// SAC on stacked frames.
    Sac(Box<SacPolicy>),
    /// DreamerV3, cRSSM or cMask.
    Dreamer(Box<DreamerPolicy>),
    /// A policy trained elsewhere, as an MLP ([`mlp`]): deterministic, without state.
    Mlp(Box<MlpPolicy>),
}

impl Policy {
    /// The policy of `agent` for LiDAR frames of `frame_dim` values with `weights`; `seed`
    /// seeds its sampling noise.
    pub fn new(agent: &AgentConfig, frame_dim: usize, weights: &[u8], seed: u64) -> Result<Self> {
        Ok(match agent.algo {
            AlgoKind::Sac => Policy::Sac(Box::new(SacPolicy::new(
                &agent.sac, frame_dim, ACT_DIM, weights, seed,
            )?)),
            AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => Policy::Dreamer(Box::new(
                DreamerPolicy::new(&agent.dreamer(), frame_dim, weights, seed)?,
            )),
        })
    }

    /// The MLP policy of the file `bytes` ([`mlp`]) for LiDAR frames of `frame_dim` values.
    pub fn mlp(bytes: &[u8], frame_dim: usize) -> Result<Self> {
        Ok(Policy::Mlp(Box::new(MlpPolicy::from_safetensors(
            bytes, frame_dim,
        )?)))
    }

    /// Replaces the weights (same architecture).
    pub fn load(&mut self, weights: &[u8]) -> Result<()> {
        match self {
            Policy::Sac(p) => p.load(weights),
            Policy::Dreamer(p) => p.load(weights),
            Policy::Mlp(p) => {
                let frame = p.frame_dim();
                **p = MlpPolicy::from_safetensors(weights, frame)?;
                Ok(())
            }
        }
    }

    /// Restarts the sampling noise from `seed` (so that an episode's sampled actions depend on
    /// its own seed only).
    pub fn reseed(&mut self, seed: u64) {
        match self {
            Policy::Sac(p) => p.reseed(seed),
            Policy::Dreamer(p) => p.reseed(seed),
            Policy::Mlp(_) => {}
        }
    }

    /// What it carries into the next episode (see [`CarriedState`]).
    pub fn carried(&self) -> CarriedState {
        match self {
            Policy::Sac(p) => p.carried(),
            Policy::Dreamer(p) => CarriedState {
                rng_words: p.rng_words(),
                frames: Vec::new(),
            },
            Policy::Mlp(_) => CarriedState::default(),
        }
    }

    /// Takes up `state`, what a policy built as this one carried ([`Policy::carried`]).
    pub fn carry(&mut self, state: &CarriedState) {
        match self {
            Policy::Sac(p) => p.carry(state),
            Policy::Dreamer(p) => p.set_rng_words(state.rng_words),
            Policy::Mlp(_) => {}
        }
    }

    /// Starts a new episode.
    pub fn reset(&mut self) {
        match self {
            Policy::Sac(p) => p.reset(),
            Policy::Dreamer(p) => p.reset(),
            Policy::Mlp(_) => {}
        }
    }

    /// Fixes cMask's mask at `mask` instead of choosing it (`None`: chosen again); the mask
    /// network still runs, so a sampling policy's noise stays that of the unfixed one.
    pub fn fix_mask(&mut self, mask: Option<[f32; 2]>) -> Result<()> {
        match self {
            Policy::Dreamer(p) => p.fix_mask(mask),
            Policy::Sac(_) | Policy::Mlp(_) if mask.is_none() => Ok(()),
            Policy::Sac(_) | Policy::Mlp(_) => Err(PolicyError::NoMask),
        }
    }

    /// The decision for the newest observation under the episode's raw context `[c_v, c_θ]`
    /// (SAC ignores it); the mode of the action distribution if `deterministic`.
    pub fn act(&mut self, obs: &[f32], context: [f32; 2], deterministic: bool) -> Result<Decision> {
        Ok(match self {
            Policy::Sac(p) => {
                let a = p.act(obs, deterministic)?;
                Decision {
                    action: [a[0], a[1]],
                    mask: None,
                }
            }
            Policy::Dreamer(p) => {
                let (action, mask) = p.act(obs, context, deterministic)?;
                Decision { action, mask }
            }
            Policy::Mlp(p) => Decision {
                action: p.act(obs, context)?,
                mask: None,
            },
        })
    }
}

#[cfg(test)]
mod old_weights;

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;

    #[test]
    fn a_policy_error_names_its_cause_once() {
        let config = PolicyError::from(AgentConfigError::OutOfRange(
            "agent.dreamer.units = 0".into(),
        ));
        let weights = PolicyError::from(WeightsError::Format("truncated header".into()));
        for (e, cause) in [
            (config, "agent.dreamer.units = 0"),
            (weights, "truncated header"),
        ] {
            assert!(e.to_string().contains(cause), "{e}");
            // no chained source: a `{:#}` chain would print the cause a second time
            assert!(e.source().is_none(), "{e}");
        }
    }
}
