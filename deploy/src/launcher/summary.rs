//! The run's closing line on where its steps went ([`step_summary`]).

use ctxrace_run::run_dir::{ACTOR_REPORTS, REPLAY_REPORT};
use std::collections::BTreeMap;
use std::path::Path;

use super::progress::{replay_streams, RestartCosts};
use super::stalls::Stalls;

/// How a run's supervision ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum RunEnd {
    /// The learner took its gradient steps.
    Trained,
    /// SIGINT (Ctrl-C) or SIGTERM stopped it.
    Interrupted,
    /// An error stopped it (the launcher's error follows the line).
    Failed,
}

impl RunEnd {
    /// The closing line's first words.
    fn said(self) -> &'static str {
        match self {
            Self::Trained => "the learner took its gradient steps",
            Self::Interrupted => "interrupted (SIGINT or SIGTERM)",
            Self::Failed => "stopped by the error below",
        }
    }

    /// Why the replay may hold fewer steps than the budget.
    fn why_short(self) -> &'static str {
        match self {
            Self::Trained => "the learner took its gradient steps first",
            Self::Interrupted => "the run was interrupted",
            Self::Failed => "the run stopped on an error",
        }
    }
}

/// One line on how the run ended (`end`) and where its steps went, from the replay's own
/// counts first: stored (of each actor), short of or past the budget, rejected, lost in replay
/// crashes; then what the actors report sending (every start of each, a killed one counted to
/// its last heartbeat), what of that is not accounted for, and dropped; the gradient steps
/// restarted learners took twice; and the longest pauses, `stalls`.
pub(super) fn step_summary(
    dir: &Path,
    costs: RestartCosts,
    stalls: &Stalls,
    end: RunEnd,
) -> String {
    let (sent, dropped) = actor_reports(dir);
    let shares: Vec<String> = sent.values().map(u64::to_string).collect();
    let total = sent.values().sum::<u64>() + costs.killed_actor_steps;
    let mut line = format!("{}; steps: ", end.said());
    let taken = read(&dir.join(REPLAY_REPORT))
        .map(|replay| replay_steps(&mut line, dir, &replay, &costs, end));
    line += &format!(
        "; the actors report {total} sent ({}{})",
        shares.join(" / "),
        match costs.killed_actor_steps {
            0 => String::new(),
            k => format!(", and {k} by killed actors to their last heartbeat"),
        }
    );
    if let Some(taken) = taken {
        let unaccounted = total.saturating_sub(taken);
        if unaccounted > 0 {
            line += &format!(
                "; {unaccounted} sent neither stored nor counted (in rejected chunks, or \
                 waiting at a replay that crashed)"
            );
        }
    }
    if dropped > 0 {
        line += &format!(
            "; {dropped} DROPPED (the replay did not take them before their actor stopped: \
             see actors/*.json)"
        );
    } else {
        line += "; none dropped";
    }
    if costs.repeated_grad_steps > 0 {
        line += &format!(
            "; {} gradient steps TAKEN TWICE (a learner restarted from its checkpoint after \
             taking them)",
            costs.repeated_grad_steps
        );
    }
    line += &pauses(stalls);
    line
}

/// The longest pauses of the run's processes, and its actors' largest policy lags.
fn pauses(s: &Stalls) -> String {
    let secs = |d: &std::time::Duration| format!("{:.1}", d.as_secs_f64());
    let actors: Vec<String> = s.actor_silence.iter().map(secs).collect();
    let lags: Vec<String> = s.actor_lag.iter().map(u64::to_string).collect();
    format!(
        "; longest pauses: learner {} s, replay {} s, actors {} s; largest policy lag {} \
         gradient steps",
        secs(&s.learner_pause),
        secs(&s.replay_silence),
        actors.join(" / "),
        lags.join(" / ")
    )
}

/// Appends to `line` what the replay of the run in `dir` took, from its report `replay` and
/// its per-actor counts: stored (of each actor), short of the budget (why: `end`) or past it,
/// rejected (by every start: those that crashed are in `costs`), its longest stall, and the
/// steps lost in its crashes (`costs`); returns the steps it took (stored, surplus or lost).
fn replay_steps(
    line: &mut String,
    dir: &Path,
    replay: &serde_json::Value,
    costs: &RestartCosts,
    end: RunEnd,
) -> u64 {
    let lost = costs.lost;
    let stored = replay["inserted"].as_u64().unwrap_or(0);
    *line += &format!("{stored} stored by the replay");
    // what the replay itself took of each actor: its count, not the actors' claims
    let streams = replay_streams(dir);
    let surplus = streams.surplus_by_actor.iter().sum::<u64>();
    if !streams.stored_by_actor.is_empty() {
        *line += &format!(" ({} of each actor", per_actor(&streams.stored_by_actor));
        // a restarted replay counts from its restart
        let restarted = replay["restored_inserts"].as_u64().unwrap_or(0) > 0;
        *line += if restarted { ", its last start)" } else { ")" };
    }
    if stored < streams.env_steps {
        *line += &format!(
            ", {} short of the run's budget of {} ({})",
            streams.env_steps - stored,
            streams.env_steps,
            end.why_short()
        );
    }
    if surplus > 0 {
        *line += &format!(
            ", {surplus} past the run's budget of {} (taken, not stored: {} of each actor)",
            streams.env_steps,
            per_actor(&streams.surplus_by_actor)
        );
    }
    *line += &format!(
        ", {} rejected{}, longest replay stall {:.1} ms",
        replay["rejected"].as_u64().unwrap_or(0) + costs.rejected_by_crashed_replays,
        if streams.rejected_by_actor.iter().any(|&n| n > 0) {
            format!(
                " (chunks of each actor {})",
                per_actor(&streams.rejected_by_actor)
            )
        } else {
            String::new()
        },
        replay["longest_turn_ms"].as_f64().unwrap_or(0.0)
    );
    if lost > 0 {
        *line += &format!(
            "; {lost} LOST in replay restarts (stored, not in the snapshot it restarted from)"
        );
    }
    stored + surplus + lost
}

/// What the actors' reports of the run in `dir` say: the steps each actor sent (every start of
/// it), by id, and the steps they dropped in all.
fn actor_reports(dir: &Path) -> (BTreeMap<u64, u64>, u64) {
    let mut sent = BTreeMap::<u64, u64>::new();
    let mut dropped = 0;
    if let Ok(entries) = std::fs::read_dir(dir.join(ACTOR_REPORTS)) {
        for report in entries.flatten().filter_map(|e| read(&e.path())) {
            let id = report["id"].as_u64().unwrap_or(0);
            *sent.entry(id).or_default() += report["sent_steps"].as_u64().unwrap_or(0);
            dropped += report["dropped_steps"].as_u64().unwrap_or(0);
        }
    }
    (sent, dropped)
}

/// A JSON report, or `None` where it is missing or unreadable.
fn read(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Per-actor counts, as "a / b / c".
fn per_actor(v: &[u64]) -> String {
    v.iter().map(u64::to_string).collect::<Vec<_>>().join(" / ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_run::results::ReplayStreams;
    use ctxrace_run::run_dir::REPLAY_STREAMS;

    #[test]
    fn the_summary_counts_steps_past_the_budget_from_the_replays_own_file() {
        let dir = tempfile::tempdir().unwrap();
        let actors = dir.path().join(ACTOR_REPORTS);
        std::fs::create_dir(&actors).unwrap();
        for (id, sent) in [(0, 1700), (1, 1500)] {
            let report = serde_json::json!({ "id": id, "sent_steps": sent, "dropped_steps": 0 });
            std::fs::write(
                actors.join(format!("actor-{id}-0.json")),
                report.to_string(),
            )
            .unwrap();
        }
        let replay = serde_json::json!({ "inserted": 3000, "rejected": 0, "longest_turn_ms": 1.0 });
        std::fs::write(dir.path().join(REPLAY_REPORT), replay.to_string()).unwrap();
        let streams = ReplayStreams {
            stored_by_actor: vec![1600, 1400],
            surplus_by_actor: vec![100, 60],
            rejected_by_actor: vec![0, 0],
            inserted: 3000,
            env_steps: 3000,
        };
        ctxrace_run::results::write_json(&dir.path().join(REPLAY_STREAMS), &streams).unwrap();
        let line = step_summary(
            dir.path(),
            RestartCosts::default(),
            &Stalls::new(2),
            RunEnd::Trained,
        );
        assert!(
            line.starts_with("the learner took its gradient steps; steps: 3000 stored by the replay (1600 / 1400 of each actor), 160 past the run's budget of 3000"),
            "{line}"
        );
        // 3200 sent, 3160 taken: 40 unaccounted for
        assert!(
            line.contains("the actors report 3200 sent (1700 / 1500)"),
            "{line}"
        );
        assert!(
            line.contains("; 40 sent neither stored nor counted"),
            "{line}"
        );
    }

    #[test]
    fn the_longest_pauses_close_the_line() {
        let stalls = Stalls {
            learner_pause: std::time::Duration::from_millis(20_340),
            replay_silence: std::time::Duration::from_millis(950),
            actor_silence: vec![std::time::Duration::from_millis(1_020); 2],
            actor_lag: vec![12, 430],
        };
        let dir = tempfile::tempdir().unwrap();
        let line = step_summary(
            dir.path(),
            RestartCosts::default(),
            &stalls,
            RunEnd::Trained,
        );
        assert!(
            line.ends_with(
                "; longest pauses: learner 20.3 s, replay 0.9 s, actors 1.0 / 1.0 s; largest \
                 policy lag 12 / 430 gradient steps"
            ),
            "{line}"
        );
        assert_eq!(stalls.to_json()["actor_largest_policy_lag"][1], 430);
        assert_eq!(stalls.to_json()["learner_longest_pause_s"], 20.3);
    }
}
