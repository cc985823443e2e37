//! The run's live figures and budget bookkeeping: steps stored and taken, policy versions,
//! episodes, and what restarts cost (steps lost, sent by killed actors, gradient steps taken
//! twice).

use ctxrace_ipc::wire::{EpisodeReport, Heartbeat, ReplayStatus, REASONS};
use ctxrace_run::results::{read_json, ReplayStreams, TrainingEpisode};
use ctxrace_run::run_dir::REPLAY_STREAMS;
use std::path::Path;
use std::time::Instant;

/// Live figures for the progress bar.
#[derive(Default)]
pub(super) struct Progress {
    /// Steps the replay stored (its newest status).
    pub(super) env_steps: u64,
    /// The learner's newest weights version: its gradient steps.
    pub(super) grad_steps: u64,
    /// The newest weights version verified so far (a restarted learner's broadcasts start
    /// lower): no actor can report driving a newer one.
    pub(super) newest_version: u64,
    /// Episodes reported.
    pub(super) episodes: u64,
    /// Each actor's env steps at its newest reported episode: their sum is an episode row's
    /// env steps while the replay's count lags behind (it reports once a second, and the first
    /// second holds the prefill and more).
    actor_steps: Vec<u64>,
    recent_progress: Vec<f64>,
    /// The replay's fill.
    pub(super) fill: u64,
    /// The replay's capacity.
    pub(super) capacity: u64,
    /// The policy version each actor last reported driving with.
    pub(super) actor_versions: Vec<u64>,
    /// The replay's newest status.
    pub(super) replay: ReplayStatus,
    /// Malformed or implausible telemetry and weights the launcher itself refused.
    pub(super) telemetry_rejected: u64,
    /// `telemetry_rejected` by reason ([`ctxrace_ipc::wire::REASONS`]).
    pub(super) telemetry_rejected_by_reason: [u64; REASONS.len()],
    /// Weights the launcher refused.
    pub(super) weights_rejected: u64,
    /// Steps the replay had stored when it last crashed, until its restart reports what its
    /// snapshot restored.
    inserted_at_crash: Option<u64>,
    /// Steps replays stored and lost in a crash (not in the snapshot they restarted from).
    pub(super) lost_in_restarts: u64,
    /// Chunks that replays which then crashed had rejected (a restart counts from 0 again), by
    /// reason ([`ctxrace_ipc::wire::REASONS`]).
    pub(super) rejected_by_crashed_replays: [u64; REASONS.len()],
    /// The env steps of the last episode row: rows never go back, though a restarted replay's
    /// count may (it restores its snapshot, not what it stored after).
    last_row_env_steps: u64,
    /// Each actor's env steps at its newest heartbeat (of its current start).
    pub(super) actor_beat_steps: Vec<u64>,
    /// Env steps sent by actor starts that died without writing their report, counted to
    /// their last heartbeat (the closing summary's "sent" reads the reports).
    pub(super) killed_actor_steps: u64,
    /// Gradient steps taken twice: those a learner had taken past its newest checkpoint when
    /// it died, which its restart, resuming from that checkpoint, takes again.
    pub(super) repeated_grad_steps: u64,
}

/// What restarts cost a run, for its closing summary.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct RestartCosts {
    /// Steps stored by a replay and lost in its crash.
    pub(super) lost: u64,
    /// Steps sent by killed actors (to their last heartbeat), which wrote no report.
    pub(super) killed_actor_steps: u64,
    /// Gradient steps a restarted learner took again.
    pub(super) repeated_grad_steps: u64,
    /// Chunks rejected by replays that then crashed (their restarts count from 0 again).
    pub(super) rejected_by_crashed_replays: u64,
}

impl Progress {
    /// The figures of a run with `actors` actors, before anything is reported.
    pub(super) fn new(actors: usize) -> Self {
        Self {
            actor_versions: vec![0; actors],
            actor_steps: vec![0; actors],
            actor_beat_steps: vec![0; actors],
            ..Self::default()
        }
    }

    /// Takes the learner's newest broadcast weights `version`; returns the newest version
    /// verified so far.
    pub(super) fn weights(&mut self, version: Option<u64>) -> u64 {
        if let Some(version) = version {
            self.grad_steps = version;
            self.newest_version = self.newest_version.max(version);
        }
        self.newest_version
    }

    /// Takes an actor's heartbeat: the policy version it drives, its env steps.
    pub(super) fn heartbeat(&mut self, hb: &Heartbeat) {
        if let Some(v) = self.actor_versions.get_mut(hb.actor_id as usize) {
            *v = hb.policy_version;
        }
        if let Some(steps) = self.actor_beat_steps.get_mut(hb.actor_id as usize) {
            *steps = hb.env_steps;
        }
    }

    /// Takes a finished episode (its actor's steps, its progress among the last 20); returns
    /// its row of the training episodes, its env steps never past `budget`
    /// ([`Progress::row_env_steps`]).
    pub(super) fn episode(&mut self, e: &EpisodeReport, budget: u64) -> TrainingEpisode {
        self.episodes += 1;
        if let Some(steps) = self.actor_steps.get_mut(e.actor_id as usize) {
            *steps = e.env_steps;
        }
        self.recent_progress.push(e.progress as f64);
        if self.recent_progress.len() > 20 {
            self.recent_progress.remove(0);
        }
        TrainingEpisode {
            env_steps: self.row_env_steps(budget),
            grad_steps: self.grad_steps,
            actor: e.actor_id,
            episode: e.episode_id,
            context_speed: e.context[0] as f64,
            context_steer: e.context[1] as f64,
            progress: e.progress as f64,
            overtakes: e.overtakes,
            a2a: e.a2a != 0,
            wall_crash: e.wall_crash != 0,
            episode_return: e.episode_return as f64,
            steps: e.steps as usize,
        }
    }

    /// Takes the replay's newest status; the first one of a restarted replay tells how many
    /// of the steps stored before the crash its snapshot restored: the rest are lost.
    pub(super) fn replay_status(&mut self, s: ReplayStatus) {
        if let Some(before) = self.inserted_at_crash.take() {
            self.lost_in_restarts += before.saturating_sub(s.restored_inserts);
        }
        self.env_steps = s.inserted;
        self.fill = s.fill;
        self.capacity = s.capacity;
        self.replay = s;
    }

    /// Takes the replay's final counts from the report it writes as it stops (its last start's:
    /// a crashed start's rejections stay carried), so that the status written after every role
    /// has stopped holds them, not the last status the replay sent before.
    pub(super) fn replay_report(&mut self, report: &serde_json::Value) {
        let count = |key: &str| report[key].as_u64();
        let r = &mut self.replay;
        for (field, key) in [
            (&mut r.inserted, "inserted"),
            (&mut r.sampled, "sampled"),
            (&mut r.fill, "fill"),
            (&mut r.capacity, "capacity"),
            (&mut r.dropped_chunks, "dropped_chunks"),
            (&mut r.rejected, "rejected"),
            (&mut r.batches, "batches"),
            (&mut r.inserted_at_last_batch, "inserted_at_last_batch"),
            (&mut r.restored_inserts, "restored_inserts"),
        ] {
            if let Some(n) = count(key) {
                *field = n;
            }
        }
        if let Some(by_reason) = report["rejected_by_reason"].as_object() {
            for (slot, name) in r.rejected_by_reason.iter_mut().zip(REASONS) {
                *slot = by_reason.get(name).and_then(|n| n.as_u64()).unwrap_or(0);
            }
        }
        if let Some(ms) = report["longest_turn_ms"].as_f64() {
            r.longest_turn_us = (ms * 1e3).round().clamp(0.0, u32::MAX as f64) as u32;
        }
        (self.env_steps, self.fill, self.capacity) = (r.inserted, r.fill, r.capacity);
    }

    /// Notes a replay crash, taking `last`, the dead replay's status not yet read.
    pub(super) fn replay_crashed(&mut self, last: Option<ReplayStatus>) {
        if let Some(s) = last {
            self.replay_status(s);
        }
        // a restart that crashed before its first status restored what the first one held,
        // and rejected nothing yet
        if self.inserted_at_crash.is_none() {
            self.inserted_at_crash = Some(self.replay.inserted);
            let rejected = std::mem::take(&mut self.replay.rejected_by_reason);
            for (carried, n) in self.rejected_by_crashed_replays.iter_mut().zip(rejected) {
                *carried += n;
            }
            self.replay.rejected = 0;
        }
    }

    /// Chunks the run's replays rejected in all, by reason: the crashed starts' and the
    /// current one's.
    pub(super) fn replay_rejected_by_reason(&self) -> [u64; REASONS.len()] {
        let mut all = self.rejected_by_crashed_replays;
        for (a, n) in all.iter_mut().zip(self.replay.rejected_by_reason) {
            *a += n;
        }
        all
    }

    /// Notes that actor `id` died; `reported` says whether its start wrote its report (else its
    /// steps to its last heartbeat are counted as sent by a killed actor).
    pub(super) fn actor_died(&mut self, id: usize, reported: bool) {
        if let Some(steps) = self.actor_beat_steps.get_mut(id) {
            if !reported {
                self.killed_actor_steps += *steps;
            }
            *steps = 0;
        }
    }

    /// Notes that the learner died; its restart resumes from the checkpoint at `resume_step`,
    /// so the gradient steps it had taken past that are taken again.
    pub(super) fn learner_died(&mut self, resume_step: u64) {
        self.repeated_grad_steps += self.grad_steps.saturating_sub(resume_step);
        self.grad_steps = self.grad_steps.min(resume_step);
    }

    /// What restarts have cost the run so far.
    pub(super) fn restart_costs(&self) -> RestartCosts {
        RestartCosts {
            lost: self.lost_in_restarts,
            killed_actor_steps: self.killed_actor_steps,
            repeated_grad_steps: self.repeated_grad_steps,
            rejected_by_crashed_replays: self.rejected_by_crashed_replays.iter().sum(),
        }
    }

    /// An episode row's env steps: the replay's count, or the actors' own while that lags (it
    /// comes once a second), never below the last row's (a restarted replay's count goes
    /// back to its snapshot's) and never past `budget`, which the replay never stores more
    /// than: the actors' counts take in steps of rejected chunks (which do not hold an actor
    /// back), and a corrupted report may claim any plausible count.
    fn row_env_steps(&mut self, budget: u64) -> u64 {
        let steps = self
            .env_steps
            .max(self.actor_steps.iter().sum())
            .max(self.last_row_env_steps)
            .min(budget);
        self.last_row_env_steps = steps;
        steps
    }

    /// Each actor's policy age: gradient steps between the learner's newest broadcast and the
    /// version the actor last reported driving with.
    pub(super) fn policy_lags(&self) -> impl Iterator<Item = u64> + '_ {
        self.actor_versions
            .iter()
            .map(|v| self.grad_steps.saturating_sub(*v))
    }

    /// The progress bar's message for a run started at `start`: gradient steps and their rate,
    /// episodes and their mean recent progress, the replay's fill, the largest policy lag and
    /// the rejections, if any.
    pub(super) fn message(&self, start: Instant) -> String {
        let secs = start.elapsed().as_secs_f64().max(1e-9);
        let mean = if self.recent_progress.is_empty() {
            0.0
        } else {
            self.recent_progress.iter().sum::<f64>() / self.recent_progress.len() as f64
        };
        let lag = self.policy_lags().max().unwrap_or(0);
        let rejected = self.replay.rejected + self.telemetry_rejected + self.weights_rejected;
        format!(
            "| {} grad ({:.1}/s) | {} episodes, progress {mean:.3} | replay {:.0}% | lag {lag}{}",
            self.grad_steps,
            self.grad_steps as f64 / secs,
            self.episodes,
            100.0 * self.fill as f64 / self.capacity.max(1) as f64,
            if rejected > 0 {
                format!(" | {rejected} rejected (status.json)")
            } else {
                String::new()
            },
        )
    }
}

/// Reads [`REPLAY_STREAMS`]; empty where the file is missing or unreadable (the checks wait for
/// the next one).
pub(super) fn replay_streams(dir: &Path) -> ReplayStreams {
    read_json(&dir.join(REPLAY_STREAMS)).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::super::stalls::Stalls;
    use super::super::summary::{step_summary, RunEnd};
    use super::*;
    use ctxrace_run::run_dir::{ACTOR_REPORTS, REPLAY_REPORT};

    fn status(inserted: u64, restored_inserts: u64) -> ReplayStatus {
        ReplayStatus {
            inserted,
            restored_inserts,
            ..ReplayStatus::default()
        }
    }

    /// The closing line of a run that trained to its end, its pauses none.
    fn closing_line(dir: &Path, p: &Progress) -> String {
        step_summary(dir, p.restart_costs(), &Stalls::new(2), RunEnd::Trained)
    }

    #[test]
    fn steps_stored_before_a_replay_crash_and_not_restored_count_as_lost() {
        let mut p = Progress::default();
        p.replay_status(status(500, 0));
        // the dead replay's last status arrives with the crash; its restart restored 300
        p.replay_crashed(Some(status(800, 0)));
        p.replay_status(status(300, 300));
        assert_eq!(p.lost_in_restarts, 500);
        p.replay_status(status(900, 300));
        assert_eq!(p.lost_in_restarts, 500);
        // two crashes before the restart's first status: counted once
        p.replay_crashed(None);
        p.replay_crashed(None);
        p.replay_status(status(850, 850));
        assert_eq!(p.lost_in_restarts, 550);
        // rejections of a replay that crashed are carried over its restarts, once
        let mut rejecting = status(900, 850);
        rejecting.rejected = 3;
        rejecting.rejected_by_reason[0] = 3;
        p.replay_status(rejecting);
        p.replay_crashed(None);
        p.replay_crashed(None);
        let mut again = status(900, 900);
        again.rejected = 2;
        again.rejected_by_reason[1] = 2;
        p.replay_status(again);
        assert_eq!(p.replay_rejected_by_reason()[..2], [3, 2]);
        assert_eq!(p.restart_costs().rejected_by_crashed_replays, 3);

        let dir = tempfile::tempdir().unwrap();
        let actors = dir.path().join(ACTOR_REPORTS);
        std::fs::create_dir(&actors).unwrap();
        for (id, sent) in [(0, 700), (1, 500)] {
            let report = serde_json::json!({ "id": id, "sent_steps": sent, "dropped_steps": 0 });
            std::fs::write(
                actors.join(format!("actor-{id}-0.json")),
                report.to_string(),
            )
            .unwrap();
        }
        let replay = serde_json::json!({ "inserted": 600, "rejected": 1, "longest_turn_ms": 1.0 });
        std::fs::write(dir.path().join(REPLAY_REPORT), replay.to_string()).unwrap();
        let line = closing_line(dir.path(), &p);
        // the last replay's 1 and the 3 of the start that crashed
        assert!(
            line.contains("600 stored by the replay, 4 rejected"),
            "{line}"
        );
        assert!(line.contains("550 LOST in replay restarts"), "{line}");
        assert!(
            line.contains("50 sent neither stored nor counted"),
            "{line}"
        );
        assert!(line.contains("none dropped"), "{line}");
        let clean = step_summary(
            dir.path(),
            RestartCosts {
                lost: 600,
                ..RestartCosts::default()
            },
            &Stalls::new(2),
            RunEnd::Interrupted,
        );
        assert!(
            !clean.contains("neither") && !clean.contains("TWICE"),
            "{clean}"
        );
        assert!(
            clean.starts_with("interrupted (SIGINT or SIGTERM); steps:"),
            "{clean}"
        );
    }

    #[test]
    fn the_replays_final_report_replaces_its_last_status() {
        let mut p = Progress::default();
        p.replay_status(status(900, 0));
        let report = serde_json::json!({
            "inserted": 1000, "sampled": 64, "fill": 1000, "capacity": 4000, "rejected": 2,
            "rejected_by_reason": { "dims": 2 }, "longest_turn_ms": 1.5,
        });
        p.replay_report(&report);
        assert_eq!(
            (p.env_steps, p.replay.inserted, p.replay.sampled),
            (1000, 1000, 64)
        );
        assert_eq!(p.replay.longest_turn_us, 1500);
        let dims = REASONS.iter().position(|&r| r == "dims").unwrap();
        assert_eq!(p.replay_rejected_by_reason()[dims], 2);
    }

    #[test]
    fn an_episode_rows_env_steps_never_pass_the_budget() {
        let mut p = Progress {
            actor_steps: vec![700, 500],
            ..Progress::default()
        };
        // the replay's count lags: the actors' own
        p.replay_status(status(1000, 0));
        assert_eq!(p.row_env_steps(3000), 1200);
        // the replay's when it is ahead, never past the budget
        p.replay_status(status(2000, 0));
        assert_eq!(p.row_env_steps(3000), 2000);
        p.actor_steps = vec![30_000, 30_009];
        assert_eq!(p.row_env_steps(3000), 3000);
        // a restarted replay's count (its snapshot's) and restarted actors' do not take rows back
        let mut p = Progress {
            actor_steps: vec![700, 500],
            ..Progress::default()
        };
        p.replay_status(status(2000, 0));
        assert_eq!(p.row_env_steps(3000), 2000);
        p.replay_crashed(None);
        p.replay_status(status(1500, 1500));
        p.actor_steps = vec![10, 500];
        assert_eq!(p.row_env_steps(3000), 2000);
    }

    #[test]
    fn steps_of_killed_actors_and_repeated_gradient_steps_are_counted() {
        let mut p = Progress {
            actor_beat_steps: vec![300, 200],
            ..Progress::default()
        };
        // actor 0 killed outright (no report), actor 1 exited after writing its report
        p.actor_died(0, false);
        p.actor_died(1, true);
        assert_eq!(
            (p.killed_actor_steps, p.actor_beat_steps.clone()),
            (300, vec![0, 0])
        );
        // the learner broadcast step 450 and died; its newest checkpoint is at 400
        p.grad_steps = 450;
        p.learner_died(400);
        // it died again before broadcasting: nothing more is counted
        p.learner_died(400);
        assert_eq!((p.repeated_grad_steps, p.grad_steps), (50, 400));
        let dir = tempfile::tempdir().unwrap();
        let actors = dir.path().join(ACTOR_REPORTS);
        std::fs::create_dir(&actors).unwrap();
        let report = serde_json::json!({ "id": 1, "sent_steps": 700, "dropped_steps": 0 });
        std::fs::write(actors.join("actor-1-0.json"), report.to_string()).unwrap();
        let line = closing_line(dir.path(), &p);
        assert!(
            line.contains("the actors report 1000 sent (700, and 300 by killed actors"),
            "{line}"
        );
        assert!(line.contains("50 gradient steps TAKEN TWICE"), "{line}");
    }
}
