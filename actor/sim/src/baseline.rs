//! Reference ego policies that need no training: pure pursuit at full raceline speed, uniform
//! random actions, and standing still.

use crate::race::RaceEnv;
use crate::rival::PurePursuit;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Which reference policy drives the ego.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BaselineKind {
    /// Pure pursuit on the raceline at full speed (capped at the ego's max speed).
    PurePursuit,
    /// Uniformly random actions in `[-1, 1]²`.
    Random,
    /// Zero speed, straight wheels.
    Still,
}

impl std::str::FromStr for BaselineKind {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "pure-pursuit" => Ok(Self::PurePursuit),
            "random" => Ok(Self::Random),
            "still" => Ok(Self::Still),
            _ => Err(format!(
                "unknown ego policy '{s}': use pure-pursuit, random or still"
            )),
        }
    }
}

/// A reference policy with its state.
pub enum Baseline {
    /// See [`BaselineKind::PurePursuit`].
    PurePursuit(PurePursuit),
    /// See [`BaselineKind::Random`].
    Random(Box<ChaCha8Rng>),
    /// See [`BaselineKind::Still`].
    Still,
}

impl Baseline {
    /// A fresh policy for an episode of `env`; `seed` drives the random policy.
    pub fn new(kind: BaselineKind, env: &RaceEnv, seed: u64) -> Self {
        match kind {
            BaselineKind::PurePursuit => {
                let cfg = env.config();
                let p = env.vehicle_params();
                Self::PurePursuit(PurePursuit::full_speed(
                    &cfg.rival,
                    cfg.max_speed,
                    p.wheelbase(),
                    cfg.max_steer,
                ))
            }
            BaselineKind::Random => Self::Random(Box::new(ChaCha8Rng::seed_from_u64(seed))),
            BaselineKind::Still => Self::Still,
        }
    }

    /// The action for the current state of `env`.
    pub fn act(&mut self, env: &RaceEnv) -> [f64; 2] {
        match self {
            Self::PurePursuit(pp) => {
                let (steer, speed) = pp.command(&env.track().raceline, env.ego_state());
                env.command_to_action(steer, speed)
            }
            Self::Random(rng) => [rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)],
            Self::Still => [0.0, -1.0],
        }
    }
}
