//! The process roles the launcher starts: `ctxrace replay`, `ctxrace learner` and
//! `ctxrace actor`. Each reads the run directory's `config.toml`, and the run's key from the
//! pipe the launcher hands it (`--key-fd`, see [`ctxrace_ipc::RunKey::hand_to`]): a role
//! started by hand has no key and stops with an error, since every message of the run is
//! sealed with it.

use crate::TrackArgs;
use anyhow::Result;
use clap::Args;
use ctxrace_config::validate::ConfigError;
use ctxrace_config::ExperimentConfig;
use ctxrace_ipc::{RunKey, KEY_FD_FLAG};
use ctxrace_nn::policy::ACT_DIM;
use ctxrace_run::run_dir::{
    ACTOR_REPORTS, CONFIG_FILE, REPLAY_REPORT, REPLAY_SNAPSHOT, REPLAY_STREAMS,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// What every role is told.
#[derive(Args, Clone, Debug)]
pub struct RoleArgs {
    /// The run directory.
    #[arg(long)]
    pub run_dir: PathBuf,
    /// The run's iceoryx2 prefix.
    #[arg(long)]
    pub prefix: String,
    /// Actors in the run.
    #[arg(long)]
    pub actors: usize,
    /// The descriptor of the pipe holding the run's key, which `ctxrace train` hands each role.
    #[arg(long = "key-fd", value_name = "FD")]
    pub key_fd: Option<i32>,
}

/// Arguments of `ctxrace actor`.
#[derive(Args)]
pub struct ActorArgs {
    #[command(flatten)]
    role: RoleArgs,
    /// This actor's id, `0..actors`.
    #[arg(long)]
    id: u32,
    /// Earlier starts of this actor (restarts draw fresh episodes).
    #[arg(long, default_value_t = 0)]
    incarnation: u64,
    #[command(flatten)]
    tracks: TrackArgs,
}

/// A test hook: a role (`replay`, `learner`, `actor`) named in this variable exits with status 1
/// as it starts, a crash that the launcher restarts, again and again (the runtime test of
/// `[supervisor] max_restarts`).
pub const CRASH_ROLE_ENV: &str = "CTXRACE_TEST_CRASH_ROLE";

/// What every role does first: crash if the tests ask it to, then make the process's
/// termination flag, so that a SIGTERM while it starts up (restoring a snapshot, loading a
/// checkpoint) stops it cleanly once it is up instead of killing it without its report; then
/// read the run's key from the pipe `args` names. Without one it stops with an error a restart
/// would meet again.
fn start_role(role: &str, args: &RoleArgs) -> Result<RunKey> {
    if std::env::var(CRASH_ROLE_ENV).is_ok_and(|r| r == role) {
        eprintln!("{role}: crashing at start, as {CRASH_ROLE_ENV} asks");
        std::process::exit(1);
    }
    ctxrace_ipc::termination_flag()?;
    let Some(fd) = args.key_fd else {
        return Err(ConfigError::new(format!(
            "`ctxrace {role}` has no run key ({KEY_FD_FLAG} is missing): every message of a run \
             is sealed with a key that `ctxrace train` draws and hands to the roles it starts \
             over a pipe; start the run with `ctxrace train` (with --resume to continue one) \
             instead of starting a role by hand"
        ))
        .into());
    };
    Ok(RunKey::from_fd(fd)?)
}

/// The run's experiment (an error is a [`ConfigError`]: a restart would meet it again).
pub fn read_experiment(run_dir: &Path) -> Result<ExperimentConfig> {
    Ok(ExperimentConfig::load(&run_dir.join(CONFIG_FILE)).map_err(ConfigError::new)?)
}

/// The replay's settings for a run: the run plan's ([`ctxrace_config::RunPlan::replay`]), its
/// snapshot in the run directory (`[replay] snapshot_path`, checked to stay inside it, names
/// it there).
pub fn replay_options(cfg: &ExperimentConfig, run_dir: &Path) -> ctxrace_config::ReplayOptions {
    let mut o = cfg.plan().replay;
    let name = o.snapshot_path.take();
    o.snapshot_path = Some(run_dir.join(name.as_deref().unwrap_or(Path::new(REPLAY_SNAPSHOT))));
    o
}

/// The replay process's arguments for a run of `actors` actors on the prefix `prefix`.
fn replay_args(
    cfg: &ExperimentConfig,
    run_dir: &Path,
    prefix: String,
    actors: usize,
) -> ctxrace_replay::ReplayArgs {
    ctxrace_replay::ReplayArgs {
        prefix,
        actors,
        obs_dim: cfg.race.lidar.beams,
        act_dim: ACT_DIM,
        options: replay_options(cfg, run_dir),
        max_policy_version: cfg.plan().gradient_steps,
        env_steps: cfg.plan().env_steps,
        sampled_at_least: ctxrace_learner::process::resume_step(run_dir)
            * cfg.agent.batch_spec().steps() as u64,
        handle_signals: true,
        streams_path: Some(run_dir.join(REPLAY_STREAMS)),
    }
}

/// Checks, before any process of the run in `run_dir` starts, that its replay could restore
/// its snapshot (when it has one), so that a damaged one stops the launch at once.
pub fn check_replay_snapshot(cfg: &ExperimentConfig, run_dir: &Path, actors: usize) -> Result<()> {
    let args = replay_args(cfg, run_dir, String::new(), actors);
    Ok(ctxrace_replay::check_restorable(&args)?)
}

/// Runs `ctxrace replay`.
pub fn replay(args: RoleArgs) -> Result<()> {
    let key = start_role("replay", &args)?;
    let cfg = read_experiment(&args.run_dir)?;
    let replay_args = replay_args(&cfg, &args.run_dir, args.prefix, args.actors);
    let s = ctxrace_replay::run(&replay_args, &key, &Default::default())?;
    tracing::info!("replay stopped: {s:?}");
    let report = serde_json::json!({
        "inserted": s.inserted,
        "sampled": s.sampled,
        "fill": s.fill,
        "capacity": s.capacity,
        "dropped_chunks": s.dropped_chunks,
        "rejected": s.rejected,
        "batches": s.batches,
        "inserted_at_last_batch": s.inserted_at_last_batch,
        "restored_inserts": s.restored_inserts,
        "rejected_by_reason": ctxrace_ipc::wire::named_reasons(&s.rejected_by_reason),
        "longest_turn_ms": s.longest_turn_us as f64 / 1e3,
        "samples_per_insert": replay_args.options.samples_per_insert,
        "min_fill": replay_args.options.min_fill,
    });
    Ok(ctxrace_run::results::write_json(
        &args.run_dir.join(REPLAY_REPORT),
        &report,
    )?)
}

/// Runs `ctxrace learner`.
pub fn learner(args: RoleArgs) -> Result<()> {
    let key = start_role("learner", &args)?;
    let experiment = read_experiment(&args.run_dir)?;
    ctxrace_learner::process::run(ctxrace_learner::process::LearnerOptions {
        prefix: args.prefix,
        key,
        actors: args.actors,
        frame_dim: experiment.race.lidar.beams,
        run_dir: args.run_dir,
        experiment,
    })?;
    Ok(())
}

/// Runs `ctxrace actor`.
pub fn actor(args: ActorArgs) -> Result<()> {
    let key = start_role("actor", &args.role)?;
    let experiment = read_experiment(&args.role.run_dir)?;
    let track = args
        .tracks
        .load(&experiment.track, &experiment.race)
        .map_err(ConfigError::new)?;
    let track = Arc::new(track);
    let report = ctxrace_actor::process::run(ctxrace_actor::process::ActorOptions {
        prefix: args.role.prefix,
        key,
        id: args.id,
        actors: args.role.actors,
        incarnation: args.incarnation,
        experiment,
        track,
    })?;
    let dir = args.role.run_dir.join(ACTOR_REPORTS);
    std::fs::create_dir_all(&dir)?;
    let name = format!("actor-{}-{}.json", args.id, args.incarnation);
    Ok(ctxrace_run::results::write_json(&dir.join(name), &report)?)
}
