//! The run's live status file ([`STATUS_FILE`]): the launcher's counters, each actor's policy
//! and stream, the replay's and the learner's own counters.

use anyhow::Result;
use ctxrace_config::validate::Causes;
use ctxrace_ipc::wire::named_reasons;
use ctxrace_run::results::{read_json, write_json, ReplayStreams};
use ctxrace_run::run_dir::{LEARNER_STATUS, STATUS_FILE};
use std::path::Path;

use super::progress::Progress;
use super::stalls::Stalls;

/// Writes the status file of the run in `dir` from the live figures `p`, the replay's
/// per-actor counts `streams` ([`status`]) and the longest pauses so far, `stalls`.
pub(super) fn write_status(
    dir: &Path,
    p: &Progress,
    streams: &ReplayStreams,
    stalls: &Stalls,
) -> Result<()> {
    let mut status = status(p, learner_status(dir), streams);
    status["stalls"] = stalls.to_json();
    write_json(&dir.join(STATUS_FILE), &status)?;
    Ok(())
}

/// The live status file's contents: `p`'s counters, each actor's policy version and its age in
/// gradient steps, rejections by reason, the replay's longest stall, and `learner`, the
/// learner's own transport counters ([`learner_status`]); each actor's steps the replay
/// stored and the chunks it rejected, from `streams` ([`super::progress::replay_streams`]).
fn status(p: &Progress, learner: serde_json::Value, streams: &ReplayStreams) -> serde_json::Value {
    let r = &p.replay;
    let actors: Vec<serde_json::Value> = p
        .actor_versions
        .iter()
        .zip(p.policy_lags())
        .enumerate()
        .map(|(id, (version, lag))| {
            serde_json::json!({
                "id": id,
                "policy_version": version,
                "policy_lag": lag,
                "stored_steps": streams.stored_by_actor.get(id),
                "surplus_steps": streams.surplus_by_actor.get(id),
                "rejected_chunks": streams.rejected_by_actor.get(id),
            })
        })
        .collect();
    serde_json::json!({
        "env_steps": p.env_steps,
        "grad_steps": p.grad_steps,
        "episodes": p.episodes,
        "actor_versions": p.actor_versions,
        "actors": actors,
        "max_policy_lag": p.policy_lags().max().unwrap_or(0),
        "replay": {
            "inserted": r.inserted,
            "sampled": r.sampled,
            "fill": r.fill,
            "capacity": r.capacity,
            "batches": r.batches,
            "dropped_chunks": r.dropped_chunks,
            "rejected": p.replay_rejected_by_reason().iter().sum::<u64>(),
            "rejected_by_reason": named_reasons(&p.replay_rejected_by_reason()),
            "restored_inserts": r.restored_inserts,
            "budget_stored": streams.budget_stored(),
            "surplus": streams.surplus_by_actor.iter().sum::<u64>(),
            "lost_in_restarts": p.lost_in_restarts,
            "longest_turn_ms": r.longest_turn_us as f64 / 1e3,
        },
        "killed_actor_steps": p.killed_actor_steps,
        "repeated_grad_steps": p.repeated_grad_steps,
        "learner": learner,
        "launcher_rejected": {
            "telemetry": p.telemetry_rejected,
            "telemetry_by_reason": named_reasons(&p.telemetry_rejected_by_reason),
            "weights": p.weights_rejected,
        },
    })
}

/// The learner's status file of its current start ([`LEARNER_STATUS`]): null before its first,
/// an `error` naming the file and the cause where it cannot be read as JSON.
pub(super) fn learner_status(dir: &Path) -> serde_json::Value {
    let path = dir.join(LEARNER_STATUS);
    if !path.exists() {
        return serde_json::Value::Null;
    }
    read_json(&path).unwrap_or_else(|e| serde_json::json!({ "error": Causes(&e).to_string() }))
}
