//! The run's own bounds and history, which every received field is checked against before it
//! changes any state: what a message claims is taken only if the run could have produced it.
//! Every message is authenticated first (its tag under the run's key), so what these checks see
//! was sent by a process of the run: a value that fails them is a replayed copy of an older
//! message or a bug, and is rejected without moving any history.

use super::wire::WireError;
use ctxrace_config::ExperimentConfig;
use std::time::{Duration, Instant};

/// Most env steps one actor takes in a second: about three times the fastest decision loop
/// measured (`ctxrace bench sim`, random actions, one rival), so a real actor never reaches it.
pub const MAX_ACTOR_STEPS_PER_SEC: f64 = 100_000.0;
/// Largest lap progress an episode reports: one lap, and at most one decision past the line.
pub const MAX_PROGRESS: f32 = 1.5;
/// Largest reward of one decision in magnitude: a speed ratio, a distance to the centreline in
/// metres, ±1 for a crash or a lap and ±1 per rival passed stay far below it.
pub const MAX_STEP_REWARD: f32 = 100.0;
/// Slack added to every time bound: messages queue between their sending and their reading.
const SLACK: Duration = Duration::from_secs(1);

/// What the messages of a run can hold, from its configuration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunBounds {
    /// The learner's gradient-step target: no weights version, and no policy version a chunk
    /// or a heartbeat names, lies beyond it.
    pub max_policy_version: u64,
    /// Most decisions in one episode (`[race] max_time` over a decision's period).
    pub max_episode_steps: u64,
    /// Contexts are drawn within `±context_range`.
    pub context_range: f32,
    /// The replay's capacity in steps: its actors' streams together.
    pub replay_capacity: u64,
    /// Rivals in each race: an episode's overtakes are at most this many a decision.
    pub rivals: u32,
}

impl RunBounds {
    /// The bounds of the run of `cfg` with `actors` actors.
    pub fn of(cfg: &ExperimentConfig, actors: usize) -> Self {
        let plan = cfg.plan();
        Self {
            max_policy_version: plan.gradient_steps,
            max_episode_steps: plan.max_episode_steps,
            context_range: cfg.train.context_range as f32,
            replay_capacity: plan.replay_capacity(actors),
            rivals: cfg.race.rivals as u32,
        }
    }
}

/// The history of one counter of one process start (an actor's env steps, the replay's
/// inserts): a value must not go back, and may grow at most `per_sec` a second over the time
/// since the last accepted one, or since the start for the first (plus [`SLACK`]). Only an
/// accepted value moves it.
#[derive(Clone, Debug)]
pub(crate) struct Counter {
    what: &'static str,
    per_sec: f64,
    since: Instant,
    /// The start's first value (a restored count the counter continues from).
    base: u64,
    last: Option<(u64, Instant)>,
}

impl Counter {
    /// A counter named `what` of a process started now, growing at most `per_sec` a second.
    pub(crate) fn new(what: &'static str, per_sec: f64) -> Self {
        Self {
            what,
            per_sec,
            since: Instant::now(),
            base: 0,
            last: None,
        }
    }

    /// Makes the counter continue from `base` (the start's first value may be anywhere up to
    /// `base` plus the rate bound; the caller checks `base` itself).
    pub(crate) fn set_base(&mut self, base: u64) {
        self.base = base;
    }

    /// Checks `got`, which must be at least `advance` past the last accepted value (an episode
    /// report's own steps); changes nothing ([`accept`](Self::accept) it after).
    pub(crate) fn check(&self, got: u64, advance: u64, now: Instant) -> Result<(), WireError> {
        let (from, at, min) = match self.last {
            Some((last, at)) => (last, at, last.saturating_add(advance)),
            None => (self.base, self.since, 0),
        };
        if got < min {
            return Err(WireError::Backwards {
                what: self.what,
                got,
                last: from,
            });
        }
        let secs = (now.saturating_duration_since(at) + SLACK).as_secs_f64();
        let most = from as f64 + advance as f64 + self.per_sec * secs;
        if got as f64 > most {
            return Err(WireError::Implausible(format!(
                "{} {got} grew from {from} faster than {} a second",
                self.what, self.per_sec
            )));
        }
        Ok(())
    }

    /// [`check`](Self::check)s `got` and takes it if it passes.
    pub(crate) fn take(&mut self, got: u64, advance: u64, now: Instant) -> Result<(), WireError> {
        self.check(got, advance, now)?;
        self.accept(got, now);
        Ok(())
    }

    /// The last accepted value.
    pub(crate) fn last(&self) -> Option<u64> {
        self.last.map(|(value, _)| value)
    }

    /// Takes `got` as the newest value.
    pub(crate) fn accept(&mut self, got: u64, now: Instant) {
        self.last = Some((got, now));
    }
}

/// Checks that a policy version named `what` lies within the learner's target `max`
/// ([`RunBounds::max_policy_version`]).
pub(crate) fn check_version(what: &str, version: u64, max: u64) -> Result<(), WireError> {
    if version > max {
        return Err(WireError::Implausible(format!(
            "{what} {version} is beyond the run's {max} gradient steps"
        )));
    }
    Ok(())
}

/// Checks that `value` lies in `[lo, hi]` (NaN does not); `what` names it.
pub(crate) fn check_range(what: &str, value: f32, lo: f32, hi: f32) -> Result<(), WireError> {
    if !(lo..=hi).contains(&value) {
        return Err(WireError::Implausible(format!(
            "{what} {value} is outside [{lo}, {hi}]"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_counter_takes_growth_within_its_rate_and_rejected_values_never_move_it() {
        let mut c = Counter::new("env steps", 10.0);
        let t0 = c.since;
        // the first value: at most 10 a second since the start, plus a second of slack
        assert!(c.check(10, 0, t0).is_ok());
        let e = c.check(11, 0, t0).unwrap_err();
        assert!(matches!(e, WireError::Implausible(_)), "{e}");
        c.accept(10, t0);
        let t2 = t0 + Duration::from_secs(2);
        assert!(c.check(40, 0, t2).is_ok());
        assert!(c.check(41, 0, t2).is_err());
        // an episode's own steps come on top of the rate, and must be there
        assert!(c.check(45, 5, t2).is_ok());
        assert!(matches!(
            c.check(14, 5, t2),
            Err(WireError::Backwards {
                got: 14,
                last: 10,
                ..
            })
        ));
        // values going back (replayed copies of older messages) or growing too fast are
        // rejected however many come, and the next real value is taken
        for old in [2, 5, 9, 10_000] {
            assert!(c.take(old, 4, t2).is_err());
        }
        assert_eq!(c.last(), Some(10));
        assert!(c.take(40, 0, t2).is_ok());
        assert_eq!(c.last(), Some(40));
        let mut restored = Counter::new("inserted", 10.0);
        restored.set_base(1000);
        assert!(restored.check(1010, 0, restored.since).is_ok());
        assert!(restored.check(1011, 0, restored.since).is_err());
    }
}
