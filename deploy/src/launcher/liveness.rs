//! Liveness: when a process counts as hung (no sign of life) or stalled (an actor's policy
//! lagging, its steps not reaching the replay, the learner taking no gradient step), and is
//! killed for it, to be restarted.

use ctxrace_config::SupervisorConfig;
use ctxrace_ipc::TRAJECTORY_BUFFER;
use ctxrace_run::results::ReplayStreams;
use std::path::Path;
use std::time::{Duration, Instant};

use super::children::{Children, Supervised};
use super::progress::Progress;
use super::stalls::{Overdue, Stalls};
use super::status::learner_status;

/// Most env steps an actor can take past what the replay stored of it without any of them
/// being stored: its chunks waiting in the replay's queue ([`TRAJECTORY_BUFFER`]), one in its
/// backlog and one being filled, one step a decision. Beyond it, the actor stepped on while
/// its chunks were taken and not stored (rejected) or lost.
const UNSTORED_SLACK: u64 = ((TRAJECTORY_BUFFER + 2) * ctxrace_ipc::wire::MAX_CHUNK) as u64;

/// Whether an actor's steps reach the replay: the replay's count of its stored steps, and the
/// actor's env steps (its heartbeat's) when that count last grew.
#[derive(Debug, Default)]
struct StreamWatch {
    stored: u64,
    beat_at_store: u64,
    starved: Overdue,
}

impl StreamWatch {
    /// Takes the replay's newest count of the actor's stored steps and the actor's newest env
    /// steps at `now`; once the actor has been more than [`UNSTORED_SLACK`] steps past the
    /// last growth of its stored count for longer than `timeout`, returns for how long.
    fn check(
        &mut self,
        stored: u64,
        beat: u64,
        now: Instant,
        timeout: Duration,
    ) -> Option<Duration> {
        if stored != self.stored {
            (self.stored, self.beat_at_store) = (stored, beat);
        }
        let starved = beat > self.beat_at_store + UNSTORED_SLACK;
        self.starved.check(starved, now, timeout)
    }

    /// A new start of the actor: its env steps count from 0 again.
    fn actor_started(&mut self) {
        self.beat_at_store = 0;
        self.starved = Overdue::default();
    }
}

/// The liveness checks of a run ([`Liveness::check`]), with what they remember between ticks.
pub(super) struct Liveness {
    /// Longest silence of a process (`[supervisor] heartbeat_timeout_secs`).
    silence: Duration,
    /// Longest stall of a process (`[supervisor] stall_timeout_secs`).
    stall: Duration,
    /// Most gradient steps an actor's policy may lag (`[supervisor] max_policy_lag`).
    max_policy_lag: u64,
    /// Steps the replay holds before it serves batches.
    min_fill: u64,
    /// Whether each actor's steps reach the replay.
    streams: Vec<StreamWatch>,
    /// The learner's gradient steps at the last check.
    last_grad_steps: u64,
    /// The longest pauses seen so far.
    pub(super) stalls: Stalls,
}

impl Liveness {
    /// The checks of `actors` actors under `cfg`, with a replay that serves from `min_fill`
    /// steps on.
    pub(super) fn new(cfg: &SupervisorConfig, min_fill: u64, actors: usize) -> Self {
        Self {
            silence: Duration::from_secs(cfg.heartbeat_timeout_secs),
            stall: Duration::from_secs(cfg.stall_timeout_secs),
            max_policy_lag: cfg.max_policy_lag,
            min_fill,
            streams: (0..actors).map(|_| StreamWatch::default()).collect(),
            last_grad_steps: 0,
            stalls: Stalls::new(actors),
        }
    }

    /// A new start of actor `id`: its env steps count from 0 again.
    pub(super) fn actor_started(&mut self, id: usize) {
        self.streams[id].actor_started();
    }

    /// Kills what is hung (the replay and the actors: no sign of life) and what is stalled:
    /// progress, not just heartbeats (weights reach every actor, each actor's steps reach the
    /// replay, whose per-actor counts `replay_took` holds, and the learner trains); a killed
    /// process is then reaped as a crash. `p` holds the live figures, `dir` the run.
    pub(super) fn check(
        &mut self,
        children: &mut Children,
        p: &Progress,
        replay_took: &ReplayStreams,
        dir: &Path,
    ) {
        let now = Instant::now();
        self.record(children, p, now);
        for proc in std::iter::once(&mut children.replay).chain(children.actors.iter_mut()) {
            proc.kill_if_silent(self.silence);
        }
        self.kill_lagging_actors(&mut children.actors, p, now);
        self.kill_starved_actors(&mut children.actors, p, replay_took, now);
        self.kill_idle_learner(children, p, dir, now);
    }

    /// Kills each actor that has driven a policy more than `max_policy_lag` gradient steps
    /// behind the learner's newest for longer than the stall timeout.
    /// Notes in [`Liveness::stalls`] how long each process has been quiet or idle at `now`,
    /// and each actor's policy lag.
    fn record(&mut self, children: &Children, p: &Progress, now: Instant) {
        let s = &mut self.stalls;
        if children.replay.running() {
            s.replay_silence = s.replay_silence.max(children.replay.quiet(now));
        }
        let actors = children.actors.iter().zip(p.policy_lags());
        for ((actor, lag), (silence, most)) in
            actors.zip(s.actor_silence.iter_mut().zip(&mut s.actor_lag))
        {
            if actor.running() {
                *silence = (*silence).max(actor.quiet(now));
                *most = (*most).max(lag);
            }
        }
        s.learner_pause = s.learner_pause.max(children.learner.stalled.held(now));
    }

    fn kill_lagging_actors(&self, actors: &mut [Supervised], p: &Progress, now: Instant) {
        for (actor, lag) in actors.iter_mut().zip(p.policy_lags()) {
            let lagging = actor.running() && lag > self.max_policy_lag;
            if let Some(held) = actor.stalled.check(lagging, now, self.stall) {
                actor.kill(&format!(
                    "has driven a policy {lag} gradient steps behind the learner's newest for \
                     {:.0} s ([supervisor] max_policy_lag = {}): the weights stopped reaching \
                     it; killing it",
                    held.as_secs_f64(),
                    self.max_policy_lag
                ));
            }
        }
    }

    /// Kills each actor that has stepped on while none of its steps reached the replay for
    /// longer than the stall timeout ([`StreamWatch`]).
    fn kill_starved_actors(
        &mut self,
        actors: &mut [Supervised],
        p: &Progress,
        replay_took: &ReplayStreams,
        now: Instant,
    ) {
        for ((actor, watch), (&stored, &beat)) in actors
            .iter_mut()
            .zip(&mut self.streams)
            .zip(replay_took.stored_by_actor.iter().zip(&p.actor_beat_steps))
        {
            if !actor.running() {
                continue;
            }
            if let Some(held) = watch.check(stored, beat, now, self.stall) {
                actor.kill(&format!(
                    "took env steps up to {beat} while none of its steps reached the replay for \
                     {:.0} s (the replay holds {stored} of them): killing it",
                    held.as_secs_f64()
                ));
            }
        }
    }

    /// Kills the learner once it has taken no gradient step for longer than the stall timeout
    /// while a live replay held enough steps to serve it.
    fn kill_idle_learner(
        &mut self,
        children: &mut Children,
        p: &Progress,
        dir: &Path,
        now: Instant,
    ) {
        let replay = &children.replay;
        let replay_serves = replay.running()
            && replay.last_sign.is_some_and(|t| t.elapsed() < self.silence)
            && p.replay.inserted >= self.min_fill;
        let learner = &mut children.learner;
        let idle = learner.running() && replay_serves && p.grad_steps == self.last_grad_steps;
        if let Some(held) = learner.stalled.check(idle, now, self.stall) {
            learner.kill(&format!(
                "took no gradient step in {:.0} s while the replay held {} steps (its own \
                 counters: {}): killing it",
                held.as_secs_f64(),
                p.replay.inserted,
                learner_status(dir)
            ));
        }
        self.last_grad_steps = p.grad_steps;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_actor_is_starved_only_when_it_steps_far_past_its_stored_steps_for_long() {
        let t0 = Instant::now();
        let (s, timeout) = (Duration::from_secs(1), Duration::from_secs(5));
        let mut watch = StreamWatch::default();
        // stored grows with the actor's steps: never starved
        for k in 0..20u64 {
            assert_eq!(
                watch.check(64 * k, 64 * k + 500, t0 + Duration::from_secs(k), timeout),
                None
            );
        }
        // held up by the replay's rate limiter: it stops within the slack, and waits
        let at = 64 * 19;
        for k in 20..40u64 {
            let beat = (64 * k + 500).min(at + UNSTORED_SLACK);
            assert_eq!(
                watch.check(at, beat, t0 + Duration::from_secs(k), timeout),
                None
            );
        }
        // stepping on while nothing it sends is stored: starved once past the timeout
        let far = at + 500 + UNSTORED_SLACK + 1;
        assert_eq!(watch.check(at, far, t0 + 40 * s, timeout), None);
        assert_eq!(watch.check(at, far + 64, t0 + 46 * s, timeout), Some(6 * s));
        // a restart counts its steps from 0 again
        watch.actor_started();
        assert_eq!(watch.check(at, 100, t0 + 47 * s, timeout), None);
        assert_eq!(watch.check(at, 200, t0 + 60 * s, timeout), None);
    }
}
