//! Experience collection: [`RaceEnv`] episodes under contexts drawn uniformly from the training
//! range, driven by a [`Policy`] (sampling its actions) or by uniform random actions while the
//! replay is prefilled. Every step goes to a sink in the replay's convention
//! ([`ctxrace_ipc::TrajectoryStep`]): an episode's first step carries its reset observation, a
//! zero action and zero reward; each later step the observation reached, the action that led
//! to it with (cMask) the context mask that chose it, and the reward received.
//!
//! [`Collector::with_paper_code_rows`] stores them as the paper's code does instead
//! (`[agent.dreamer] step_alignment = "paper-code"`, c0fd903 `Planners/*DreamerPlanners.py`
//! `add_memory_entry`): one row per decision holding the observation, the action chosen at it
//! (and its mask) and the reward that followed, flagged terminal or last when the episode ended
//! after it; an episode's last observation is never stored.
//!
//! The inline trainer (as its [`ExperienceSource`]) and the actor process both run this; only
//! their sinks differ.

use ctxrace_config::{Context, ExperimentConfig};
use ctxrace_ipc::TrajectoryStep;
use ctxrace_nn::policy::PolicyError;
use ctxrace_nn::Policy;
use ctxrace_run::experience::{EndedEpisode, ExperienceSource, SourcePosition};
use ctxrace_run::results::TrainingEpisode;
use ctxrace_sim::race::{EpisodeMetrics, RaceEnv};
use ctxrace_sim::RaceError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Why a decision could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum CollectError {
    /// The policy could not act on the observation.
    #[error(transparent)]
    Policy(#[from] PolicyError),
    /// The race refused the action.
    #[error(transparent)]
    Race(#[from] RaceError),
}

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
    /// The mean of the context masks the policy chose, and their count (`None`: no mask).
    pub mean_mask: Option<([f64; 2], u64)>,
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
    /// Rows as the paper's code stores them ([`Collector::with_paper_code_rows`]).
    paper_code_rows: bool,
    /// The next decision is the running episode's first.
    first_decision: bool,
    /// Sums of the running episode's context masks, and their count.
    mask_sums: ([f64; 2], u64),
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
            paper_code_rows: false,
            first_decision: false,
            mask_sums: ([0.0; 2], 0),
        }
    }

    /// The collector `cfg` asks for on `env`: contexts from its training range, rows as its
    /// agent stores them; `seed` as in [`Collector::new`].
    pub fn for_experiment(env: RaceEnv, cfg: &ExperimentConfig, seed: u64) -> Self {
        Self::new(env, cfg.train.context_range, seed)
            .with_paper_code_rows(cfg.agent.stores_paper_code_rows())
    }

    /// The same collector storing rows as the paper's code does when `on` (see the module
    /// doc; [`ctxrace_config::AgentConfig::stores_paper_code_rows`]).
    pub fn with_paper_code_rows(self, on: bool) -> Self {
        Self {
            paper_code_rows: on,
            ..self
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
    ) -> Result<Option<Finished>, CollectError> {
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
            self.first_decision = true;
            self.mask_sums = ([0.0; 2], 0);
            if !self.paper_code_rows {
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
        }
        let first_decision = std::mem::take(&mut self.first_decision);
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
        if let Some(m) = mask {
            let (sums, n) = &mut self.mask_sums;
            sums[0] += f64::from(m[0]);
            sums[1] += f64::from(m[1]);
            *n += 1;
        }
        let step = self.env.step(action.map(f64::from))?;
        self.decisions += 1;
        let last = step.terminated || step.truncated;
        // the paper's code: the observation the action was chosen at; ctxrace: the one reached
        let seen = std::mem::replace(&mut self.obs, step.obs);
        sink(&TrajectoryStep {
            obs: if self.paper_code_rows {
                &seen
            } else {
                &self.obs
            },
            action: &action,
            reward: step.reward as f32,
            is_first: self.paper_code_rows && first_decision,
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
            mean_mask: match self.mask_sums {
                (_, 0) => None,
                (sums, n) => Some((sums.map(|s| s / n as f64), n)),
            },
        }))
    }
}

impl ExperienceSource for Collector {
    type Policy = Policy;
    type Error = CollectError;

    fn obs_dim(&self) -> usize {
        self.env.obs_dim()
    }

    fn decisions(&self) -> u64 {
        Collector::decisions(self)
    }

    fn episodes(&self) -> u64 {
        Collector::episodes(self)
    }

    fn at_episode_boundary(&self) -> bool {
        Collector::at_episode_boundary(self)
    }

    fn step(
        &mut self,
        policy: Option<&mut Policy>,
        sink: &mut dyn FnMut(&TrajectoryStep),
    ) -> Result<Option<EndedEpisode>, CollectError> {
        let finished = Collector::step(self, policy, sink)?;
        Ok(finished.map(|f| EndedEpisode {
            record: TrainingEpisode {
                env_steps: 0,
                grad_steps: 0,
                actor: 0,
                episode: f.episode,
                context_speed: f.context.speed,
                context_steer: f.context.steer,
                progress: f.metrics.progress,
                overtakes: f.metrics.overtakes,
                a2a: f.metrics.a2a,
                wall_crash: f.metrics.wall_crash,
                episode_return: f.metrics.episode_return,
                steps: f.metrics.steps,
            },
            by_policy: f.by_policy,
            mean_mask: f.mean_mask,
        }))
    }

    fn position(&self) -> Option<SourcePosition> {
        Collector::at_episode_boundary(self).then(|| SourcePosition {
            decisions: self.decisions,
            episodes: self.episode,
            rng_words: self.rng.get_word_pos(),
        })
    }

    fn restore(&mut self, at: &SourcePosition) {
        self.decisions = at.decisions;
        self.episode = at.episodes;
        self.rng.set_word_pos(at.rng_words);
        self.running = false;
    }
}

fn c_f32(c: f64) -> f32 {
    c as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_config::RaceConfig;
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

    /// A row as the test compares it: observation, action, reward, first, terminal, last.
    type Row = (Vec<f32>, [f32; 2], f32, bool, bool, bool);

    /// Two three-decision episodes (timed out, stored as terminal), random actions: ctxrace
    /// stores four rows each, `(o_0, 0, 0)` first and `(o_t, a_{t−1}, r_t)` after; the paper
    /// code's form stores three, `(o_t, a_t, r_{t+1})` with the first flag on `o_0` and the
    /// terminal and last flags on `o_2`, `o_3` never stored.
    #[test]
    fn paper_code_rows_hold_the_action_chosen_at_the_observation_and_drop_the_last_one() {
        let track = Arc::new(Track::load("generated:0", &TrackOptions::default()).unwrap());
        let mut race = RaceConfig {
            timeout_is_terminal: true,
            ..RaceConfig::default()
        };
        race.max_time = 3.0 * race.physics_steps_per_action as f64 * 0.01;
        let rows = |paper_code: bool| -> Vec<Vec<Row>> {
            let env = RaceEnv::new(track.clone(), race.clone()).unwrap();
            let mut c = Collector::new(env, 0.15, 7).with_paper_code_rows(paper_code);
            let mut rows = Vec::new();
            while c.episodes() < 2 || !c.at_episode_boundary() {
                c.step(None, |s| {
                    let action = [s.action[0], s.action[1]];
                    let flags = (s.is_first, s.is_terminal, s.is_last);
                    rows.push((s.obs.to_vec(), action, s.reward, flags.0, flags.1, flags.2));
                })
                .unwrap();
            }
            rows.split_inclusive(|r: &Row| r.5)
                .map(|episode| episode.to_vec())
                .collect()
        };
        let (ours, code) = (rows(false), rows(true));
        assert_eq!((ours.len(), code.len()), (2, 2));
        for (ep, code_ep) in ours.iter().zip(&code) {
            assert_eq!((ep.len(), code_ep.len()), (4, 3), "three decisions");
            assert!(ep[0].3 && ep[0].1 == [0.0; 2] && ep[3].4 && ep[3].5);
            for (t, row) in code_ep.iter().enumerate() {
                let (seen, next) = (&ep[t], &ep[t + 1]);
                let want = (seen.0.clone(), next.1, next.2, t == 0, next.4, next.5);
                assert_eq!(*row, want, "row {t}");
            }
        }
    }
}
