//! Experience collection: [`RaceEnv`] episodes under contexts drawn uniformly from the training
//! range, driven by a [`Policy`] (sampling its actions) or by uniform random actions while the
//! replay is prefilled. Every step goes to a sink in the replay's convention
//! ([`ctxrace_common::ipc::TrajectoryStep`]): an episode's first step carries its reset observation, a
//! zero action and zero reward; each later step the observation reached, the action that led
//! to it with (cMask) the context mask that chose it, and the reward received.
//!
//! The inline trainer and the actor process both run this; only their sinks differ.

use crate::race::{EpisodeMetrics, RaceEnv};
use anyhow::Result;
use ctxrace_common::ipc::TrajectoryStep;
use ctxrace_common::{Context, Policy};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A finished episode.
#[derive(Clone, Debug)]
pub struct Finished {
    /// Index of the episode within this collector.
    pub episode: u64,
    /// Its context.
    pub context: Context,
    /// Its metrics.
    pub metrics: EpisodeMetrics,
    /// The policy chose every action of the episode (no random prefill action).
    pub by_policy: bool,
}

/// Runs episodes one decision at a time.
pub struct Collector {
    env: RaceEnv,
    rng: ChaCha8Rng,
    context_range: f64,
    episode: u64,
    obs: Vec<f32>,
    context: Context,
    running: bool,
    decisions: u64,
    /// Random actions taken in the running episode.
    random_actions: u64,
}

impl Collector {
    /// A collector on `env` drawing each context value from `U[−context_range, context_range]`;
    /// `seed` drives the contexts, the episode seeds and the random actions.
    pub fn new(env: RaceEnv, context_range: f64, seed: u64) -> Self {
        Self {
            env,
            rng: ChaCha8Rng::seed_from_u64(seed),
            context_range,
            episode: 0,
            obs: Vec::new(),
            context: Context::default(),
            running: false,
            decisions: 0,
            random_actions: 0,
        }
    }

    /// Decisions taken so far.
    pub fn decisions(&self) -> u64 {
        self.decisions
    }

    /// Episodes started so far.
    pub fn episodes(&self) -> u64 {
        self.episode
    }

    /// The environment.
    pub fn env(&self) -> &RaceEnv {
        &self.env
    }

    /// Whether the next [`Collector::step`] starts a new episode.
    pub fn at_episode_boundary(&self) -> bool {
        !self.running
    }

    /// Takes one decision with `policy` (uniform random actions when `None`), starting an
    /// episode first if none is running; passes the steps to `sink` and returns the episode
    /// if it ended.
    pub fn step(
        &mut self,
        policy: Option<&mut Policy>,
        mut sink: impl FnMut(&TrajectoryStep),
    ) -> Result<Option<Finished>> {
        let r = self.context_range;
        let mut policy = policy;
        if !self.running {
            self.context = Context {
                speed: self.rng.random_range(-r..=r),
                steer: self.rng.random_range(-r..=r),
            };
            let seed = self.rng.random();
            self.obs = self.env.reset(seed, self.context);
            if let Some(p) = policy.as_deref_mut() {
                p.reset();
            }
            self.running = true;
            self.episode += 1;
            self.random_actions = 0;
            sink(&TrajectoryStep {
                obs: &self.obs,
                action: &[0.0; 2],
                reward: 0.0,
                is_first: true,
                is_terminal: false,
                is_last: false,
                context: [c_f32(self.context.speed), c_f32(self.context.steer)],
                mask: None,
            });
        }
        let context = [c_f32(self.context.speed), c_f32(self.context.steer)];
        let (action, mask) = match policy {
            Some(p) => {
                let d = p.act(&self.obs, context, false)?;
                (d.action, d.mask)
            }
            None => {
                self.random_actions += 1;
                (
                    [
                        self.rng.random_range(-1.0..=1.0),
                        self.rng.random_range(-1.0..=1.0),
                    ],
                    None,
                )
            }
        };
        let step = self.env.step(action.map(f64::from))?;
        self.decisions += 1;
        let last = step.terminated || step.truncated;
        self.obs = step.obs;
        sink(&TrajectoryStep {
            obs: &self.obs,
            action: &action,
            reward: step.reward as f32,
            is_first: false,
            is_terminal: step.terminated,
            is_last: last,
            context,
            mask,
        });
        if !last {
            return Ok(None);
        }
        self.running = false;
        Ok(Some(Finished {
            episode: self.episode - 1,
            context: self.context,
            metrics: self.env.metrics().clone(),
            by_policy: self.random_actions == 0,
        }))
    }
}

fn c_f32(c: f64) -> f32 {
    c as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_common::RaceConfig;
    use ctxrace_tracks::{Track, TrackOptions};
    use std::sync::Arc;

    #[test]
    fn episodes_start_with_a_first_step_and_end_with_a_last_one() {
        let track = Arc::new(Track::load("generated:0", &TrackOptions::default()).unwrap());
        let env = RaceEnv::new(track, RaceConfig::default()).unwrap();
        let mut c = Collector::new(env, 0.15, 3);
        let mut flags = Vec::new();
        let mut finished = Vec::new();
        while finished.len() < 2 {
            if let Some(f) = c
                .step(None, |s| {
                    assert!(s.context.iter().all(|v| v.abs() <= 0.15));
                    flags.push((s.is_first, s.is_last, s.action == [0.0; 2]))
                })
                .unwrap()
            {
                finished.push(f);
            }
        }
        let episodes: Vec<_> = flags.split_inclusive(|f| f.1).collect();
        assert_eq!(episodes.len(), 2);
        for ep in episodes {
            assert!(ep[0].0 && ep[0].2, "first step: is_first, zero action");
            assert!(ep[1..].iter().all(|f| !f.0));
            assert!(ep.last().unwrap().1);
        }
        assert_eq!(c.decisions() as usize, flags.len() - 2);
        assert_ne!(finished[0].context, finished[1].context);
    }
}
