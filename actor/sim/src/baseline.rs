//! Reference ego policies that need no training: pure pursuit at full raceline speed,
//! follow-the-gap on the ego's own exact scan, uniform random actions, and standing still.

use crate::collision::CarBox;
use crate::gap::FollowTheGap;
use crate::race::RaceEnv;
use crate::rival::PurePursuit;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Which reference policy drives the ego.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BaselineKind {
    /// Pure pursuit on the raceline at full speed (capped at the ego's max speed).
    PurePursuit,
    /// Follow-the-gap on an exact scan of the ego's pose, context-free, with the parameters of
    /// `[rival.follow_the_gap]` (speed capped at the ego's max speed).
    FollowTheGap,
    /// Uniformly random actions in `[-1, 1]²`.
    Random,
    /// Zero speed, straight wheels.
    Still,
}

impl std::str::FromStr for BaselineKind {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Self::ALL.iter().map(|k| k.name()).collect();
                format!("unknown ego policy '{s}': use {}", names.join(", "))
            })
    }
}

impl BaselineKind {
    /// Every reference policy.
    pub const ALL: [BaselineKind; 4] = [
        Self::PurePursuit,
        Self::FollowTheGap,
        Self::Random,
        Self::Still,
    ];

    /// The name it is parsed from (`pure-pursuit`, `follow-the-gap`, `random`, `still`).
    pub fn name(self) -> &'static str {
        match self {
            Self::PurePursuit => "pure-pursuit",
            Self::FollowTheGap => "follow-the-gap",
            Self::Random => "random",
            Self::Still => "still",
        }
    }
}

impl std::fmt::Display for BaselineKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A reference policy with its state.
pub enum Baseline {
    /// See [`BaselineKind::PurePursuit`].
    PurePursuit(PurePursuit),
    /// See [`BaselineKind::FollowTheGap`].
    FollowTheGap(Box<FollowTheGap>),
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
            BaselineKind::FollowTheGap => {
                let cfg = env.config();
                Self::FollowTheGap(Box::new(FollowTheGap::reference(
                    &cfg.rival.follow_the_gap,
                    cfg.max_speed,
                    cfg.max_steer,
                    env.vehicle_params().width,
                )))
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
            Self::FollowTheGap(gap) => {
                let params = env.vehicle_params();
                let rivals: Vec<CarBox> = env.cars()[1..]
                    .iter()
                    .map(|c| CarBox::new(&c.vehicle.state, params))
                    .collect();
                let (steer, speed) = gap.command(&env.track().walls, &rivals, env.ego_state());
                env.command_to_action(steer, speed)
            }
            Self::Random(rng) => [rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0)],
            Self::Still => [0.0, -1.0],
        }
    }
}
