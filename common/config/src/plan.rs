//! What a run is held to, derived once from its experiment ([`RunPlan`]): its env-step budget,
//! its gradient-step target, the replay its processes share and the longest episode. The
//! launcher, the replay, the learner, the actors, the transport's bounds and the
//! single-process trainer all read these numbers here, never the experiment's keys they come
//! from.
//!
//! With `B·T` the steps of one training batch (`B` for a transition batch), `N` the env-step
//! budget, `P` the prefill and `ρ` the train ratio:
//!
//! - gradient steps `G = round((N − P)·ρ)` (`P = 0` with `[agent] warmup = "episodes"`,
//!   whose warm-up length is not known in advance: then `G` is the most the run can take);
//! - the replay samples `ρ·B·T` steps per inserted step, after at least `P` inserts.

use crate::replay::stream_capacity;
use crate::{ExperimentConfig, ReplayOptions, Warmup};

/// What the run of an experiment is held to ([`ExperimentConfig::plan`]).
#[derive(Clone, Debug, PartialEq)]
pub struct RunPlan {
    /// Env steps (decisions) collected in all (`[train] env_steps`): the replay stores no
    /// more, the single-process trainer takes no more, and no record counts past it.
    pub env_steps: u64,
    /// Gradient steps the learner takes in all (`G` above): its last weights version, and the
    /// highest policy version a message may name.
    pub gradient_steps: u64,
    /// Gradient steps per env step after the warm-up (`ρ`, `[train] train_ratio`).
    pub train_ratio: f64,
    /// The run's replay: `[replay]` with its sampling ratio `ρ·B·T`, its minimum fill at least
    /// the prefill, its seed `[train] seed` and its sampler `[agent] sampler`.
    pub replay: ReplayOptions,
    /// Most decisions in one episode (`[race] max_time` over a decision's period).
    pub max_episode_steps: u64,
}

impl RunPlan {
    /// The plan of `cfg`'s run.
    pub fn of(cfg: &ExperimentConfig) -> Self {
        let t = &cfg.train;
        let before = match cfg.agent.warmup {
            Warmup::RandomSteps => t.prefill,
            Warmup::Episodes => 0,
        };
        let replay = ReplayOptions {
            samples_per_insert: t.train_ratio * cfg.agent.batch_spec().steps() as f64,
            min_fill: cfg.replay.min_fill.max(t.prefill as usize),
            seed: t.seed,
            sampler: cfg.agent.sampler,
            ..cfg.replay.clone()
        };
        Self {
            env_steps: t.env_steps,
            gradient_steps: (t.env_steps.saturating_sub(before) as f64 * t.train_ratio).round()
                as u64,
            train_ratio: t.train_ratio,
            replay,
            max_episode_steps: cfg.race.max_decisions() as u64,
        }
    }

    /// Gradient steps due once `decisions` decisions are taken, the warm-up having ended after
    /// decision `warmup_end`: `round((decisions − warmup_end)·ρ)`, so that a run whose warm-up
    /// ends after the prefill is due `G` at its last decision.
    pub fn gradient_steps_due(&self, decisions: u64, warmup_end: u64) -> u64 {
        (decisions.saturating_sub(warmup_end) as f64 * self.train_ratio).round() as u64
    }

    /// Steps each of `actors` actors' streams of the replay holds.
    pub fn stream_capacity(&self, actors: usize) -> usize {
        stream_capacity(self.replay.capacity, actors)
    }

    /// Steps the replay of `actors` actors holds: its streams together.
    pub fn replay_capacity(&self, actors: usize) -> u64 {
        (self.stream_capacity(actors) * actors.max(1)) as u64
    }
}

#[cfg(test)]
mod tests {
    use crate::ExperimentConfig;

    #[test]
    fn the_plan_derives_the_runs_numbers_from_its_keys() {
        let mut cfg = ExperimentConfig::default();
        cfg.train.env_steps = 100_000;
        cfg.train.prefill = 2_500;
        cfg.train.train_ratio = 1.0;
        cfg.train.seed = 7;
        cfg.replay.min_fill = 1000;
        cfg.replay.capacity = 1000;
        let plan = cfg.plan();
        assert_eq!((plan.env_steps, plan.gradient_steps), (100_000, 97_500));
        assert_eq!(plan.replay.min_fill, 2_500);
        assert_eq!(plan.replay.seed, 7);
        let steps = cfg.agent.batch_spec().steps() as f64;
        assert_eq!(plan.replay.samples_per_insert, steps);
        // 3 actors share 1000 steps as 333 each
        assert_eq!(
            (plan.stream_capacity(3), plan.replay_capacity(3)),
            (333, 999)
        );
        assert_eq!(plan.gradient_steps_due(100_000, 2_500), plan.gradient_steps);
        assert_eq!(plan.gradient_steps_due(2_600, 2_500), 100);
        cfg.train.train_ratio = 0.5;
        assert_eq!(cfg.plan().gradient_steps, 48_750);
    }
}
