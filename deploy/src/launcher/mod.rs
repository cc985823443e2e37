//! The launcher of `ctxrace train`: starts the replay, the learner and `N` actors as child
//! processes of this binary on a fresh iceoryx2 prefix, shows one progress bar, writes the
//! training episodes, restarts crashed processes with back-off, and stops everything cleanly at
//! the end or on Ctrl-C/SIGTERM; finally it removes the run's shared memory.
//!
//! - [`children`]: a child process, its restarts with back-off (an actor draws fresh episodes,
//!   the learner resumes from its newest checkpoint, the replay from its snapshot) and its stop;
//!   each child's tracing output goes to `<run>/logs/<role>.log` (level info unless `RUST_LOG`
//!   says otherwise);
//! - [`mod@supervise`]: the supervision loop, one named step after the other each tick;
//! - [`liveness`]: when a process counts as hung or stalled, and is killed;
//! - [`stalls`]: the longest pauses a run has seen, whether or not they reached a timeout;
//! - [`progress`]: the live figures, the episode rows and what restarts cost;
//! - [`status`]: the run's live status file;
//! - [`summary`]: the closing line on where the run's steps went;
//! - [`cleanup`]: the shared memory of runs whose launcher died (removed before the run
//!   starts), of crashed processes' nodes and of the run itself;
//! - [`bus_error`]: what the launcher says when a segment is truncated under it (SIGBUS).
//!
//! The replay stores `[train] env_steps` steps and no more (its rate limiter holds the actors to
//! the learner's pace meanwhile; once the budget is stored they wait, idle). The run ends when
//! the learner has taken its gradient steps (it exits by itself; it can be up to `[replay]
//! error_buffer_steps` ahead of the actors, and a replay restart loses the steps after its
//! snapshot: then fewer are stored). Then the actors, the replay and the learner are stopped
//! together: the replay takes the actors' last chunks whatever its limiter says (past the budget
//! as surplus), so that a clean run drops no step.

mod bus_error;
mod children;
mod cleanup;
mod liveness;
mod progress;
mod stalls;
mod status;
mod summary;
mod supervise;

use crate::TrackArgs;
use anyhow::{bail, Context as _, Result};
use ctxrace_config::ExperimentConfig;
use ctxrace_ipc::{claim_run, run_prefix, RunKey, RunTransport};
use ctxrace_run::lock::DirLock;
use ctxrace_run::results::read_json;
use ctxrace_run::run_dir::{LOGS, REPLAY_REPORT};
use std::path::Path;

use bus_error::explain_bus_errors;
use children::{Children, Inherited, Supervised};
use cleanup::{remove_run, sweep_dead_runs};
use progress::replay_streams;
use status::write_status;
use summary::{step_summary, RunEnd};
use supervise::supervise;

/// Runs a training run with `actors` actor processes in `dir` (which holds `config.toml`).
pub fn run(
    cfg: &ExperimentConfig,
    dir: &Path,
    lock: &DirLock,
    actors: usize,
    tracks: &TrackArgs,
) -> Result<()> {
    explain_bus_errors();
    if actors == 0 {
        bail!("--actors must be at least 1");
    }
    let run_id = format!(
        "{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis())
    );
    sweep_dead_runs();
    let prefix = run_prefix(&run_id);
    claim_run(&prefix)?;
    // the run's key, fresh for each launch: only this process and its children hold it
    let key = RunKey::generate()?;
    let inherited = Inherited {
        lock: lock.try_clone()?,
        key: key.clone(),
    };
    let mut children = processes(dir, &prefix, &inherited, actors, tracks)?;
    let transport = RunTransport::open(&prefix, actors, "launcher", &key)?;
    let mut run = supervise(cfg, dir, &transport, &mut children);
    children.stop()?;
    drop(transport);
    remove_run(&prefix);
    // the last status, after every role's final counts: the replay's report as it stopped
    if let Ok(report) = read_json(&dir.join(REPLAY_REPORT)) {
        run.p.replay_report(&report);
    }
    if let Err(e) = write_status(dir, &run.p, &replay_streams(dir), &run.stalls) {
        eprintln!("warning: the run's last status.json: {e:#}");
    }
    let end = run.end.as_ref().map_or(RunEnd::Failed, |&end| end);
    eprintln!("{}", step_summary(dir, run.costs, &run.stalls, end));
    run.end.map(|_| ())
}

/// The run's processes, not started yet: each a subcommand of this binary on the run in `dir`
/// and the shared memory of `prefix`, with `actors` actors driving on `tracks`, each holding
/// the lock and handed the key of `inherited`.
fn processes(
    dir: &Path,
    prefix: &str,
    inherited: &Inherited,
    actors: usize,
    tracks: &TrackArgs,
) -> Result<Children> {
    let common = |role: &str| {
        vec![
            role.to_string(),
            "--run-dir".into(),
            dir.display().to_string(),
            "--prefix".into(),
            prefix.to_string(),
            "--actors".into(),
            actors.to_string(),
        ]
    };
    let logs = dir.join(LOGS);
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    Ok(Children {
        replay: Supervised::new(
            "replay".into(),
            common("replay"),
            &logs,
            inherited.try_clone()?,
        ),
        learner: Supervised::new(
            "learner".into(),
            common("learner"),
            &logs,
            inherited.try_clone()?,
        ),
        actors: (0..actors)
            .map(|k| {
                let mut args = common("actor");
                args.extend(["--id".into(), k.to_string()]);
                args.extend(track_flags(tracks));
                Ok(Supervised::actor(
                    k,
                    args,
                    dir,
                    &logs,
                    inherited.try_clone()?,
                ))
            })
            .collect::<Result<_>>()?,
    })
}

/// The flags that reproduce `tracks` on a child's command line.
fn track_flags(tracks: &TrackArgs) -> Vec<String> {
    let mut v = Vec::new();
    if let Some(d) = &tracks.tracks_dir {
        v.extend(["--tracks-dir".into(), d.display().to_string()]);
    }
    if tracks.raceline_file {
        v.push("--raceline-file".into());
    }
    for (flag, value) in [
        ("--v-max", tracks.v_max),
        ("--a-lat", tracks.a_lat),
        ("--a-long", tracks.a_long),
    ] {
        if let Some(x) = value {
            v.extend([flag.into(), x.to_string()]);
        }
    }
    v
}
