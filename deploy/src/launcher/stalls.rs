//! Pauses: how long a condition that must not last has held ([`Overdue`]), and the longest
//! pauses a run has seen ([`Stalls`]), which the liveness checks note and `status.json` and the
//! closing line report.

use std::time::{Duration, Instant};

/// How long a condition that must not last has held (an actor's policy lagging, a learner
/// taking no gradient step).
#[derive(Debug, Default)]
pub(super) struct Overdue {
    since: Option<Instant>,
}

impl Overdue {
    /// Notes whether the condition `holds` at `now`; once it has held for longer than
    /// `timeout` without a break, returns for how long.
    pub(super) fn check(
        &mut self,
        holds: bool,
        now: Instant,
        timeout: Duration,
    ) -> Option<Duration> {
        if !holds {
            self.since = None;
            return None;
        }
        let held = now.saturating_duration_since(*self.since.get_or_insert(now));
        (held > timeout).then_some(held)
    }

    /// How long the condition has held without a break at `now` (zero when it does not).
    pub(super) fn held(&self, now: Instant) -> Duration {
        self.since
            .map_or(Duration::ZERO, |since| now.saturating_duration_since(since))
    }
}

/// The longest pauses a run has seen, whether or not they reached a timeout: a process
/// stopped for a while (SIGSTOP, a swapped-out machine) leaves its trace here, in
/// `status.json` and in the closing line.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct Stalls {
    /// Longest time the learner took no gradient step while the replay served batches.
    pub(super) learner_pause: Duration,
    /// Longest time the replay sent no status.
    pub(super) replay_silence: Duration,
    /// Longest time each actor sent no heartbeat.
    pub(super) actor_silence: Vec<Duration>,
    /// Largest policy lag (gradient steps behind the learner's newest) each actor drove with.
    pub(super) actor_lag: Vec<u64>,
}

impl Stalls {
    /// The record of a run of `actors` actors, before anything is seen.
    pub(super) fn new(actors: usize) -> Self {
        Self {
            actor_silence: vec![Duration::ZERO; actors],
            actor_lag: vec![0; actors],
            ..Self::default()
        }
    }

    /// The record as `status.json` holds it (seconds, gradient steps).
    pub(super) fn to_json(&self) -> serde_json::Value {
        let secs = |d: &Duration| (d.as_secs_f64() * 10.0).round() / 10.0;
        serde_json::json!({
            "learner_longest_pause_s": secs(&self.learner_pause),
            "replay_longest_silence_s": secs(&self.replay_silence),
            "actor_longest_silence_s": self.actor_silence.iter().map(secs).collect::<Vec<_>>(),
            "actor_largest_policy_lag": self.actor_lag,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_condition_is_overdue_only_after_holding_past_its_timeout_without_a_break() {
        let t0 = Instant::now();
        let (s, timeout) = (Duration::from_secs(1), Duration::from_secs(5));
        let mut overdue = Overdue::default();
        assert_eq!(overdue.check(true, t0, timeout), None);
        assert_eq!(overdue.check(true, t0 + 5 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 6 * s, timeout), Some(6 * s));
        // a break starts it over
        assert_eq!(overdue.check(false, t0 + 7 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 8 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 13 * s, timeout), None);
        assert_eq!(overdue.check(true, t0 + 14 * s, timeout), Some(6 * s));
    }
}
