//! `ctxrace`: one command line for tracks, races, training, evaluation, reports and benchmarks;
//! the training processes (actor, replay, learner) are its subcommands too.

mod bench;
mod bench_ipc;
mod bench_learner;
mod download;
mod ego;
mod eval;
mod export_cmd;
mod figures;
mod first_look;
mod groups;
mod launcher;
mod paper;
mod parity;
mod progress;
mod race_cmd;
mod report;
mod roles;
mod shell;
mod slurm;
mod sweep;
mod table;
mod track_cmd;
mod train;
mod vehicle_cmd;

use anyhow::{Context as _, Result};
use clap::{Args, Parser, Subcommand};
use ctxrace_config::validate::{ConfigError, CONFIG_EXIT_CODE};
use ctxrace_config::RaceConfig;
use ctxrace_tracks::{Track, TrackOptions};
use std::path::PathBuf;

/// Context-aware model-based RL for head-to-head autonomous racing (F1TENTH / Roboracer).
#[derive(Parser)]
#[command(name = "ctxrace", version, about, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Inspect a track or export its computed raceline.
    #[command(subcommand)]
    Track(track_cmd::TrackCommand),
    /// Drive the vehicle model open-loop from a CSV of commands and print its states.
    Vehicle(vehicle_cmd::VehicleArgs),
    /// Run one race episode and print its metrics (optionally render it and write a trace).
    Race(race_cmd::RaceArgs),
    /// Measure speeds.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Tables (Markdown and CSV, as in the paper) and figures from evaluation and training runs.
    Report(report::ReportArgs),
    /// Train an agent (inline, or with actor, replay and learner processes).
    Train(train::TrainArgs),
    /// Run the paper's evaluation protocol on a checkpoint or a reference policy.
    Eval(eval::EvalArgs),
    /// Export a trained agent for use outside ctxrace (ONNX).
    #[command(subcommand)]
    Export(export_cmd::ExportCommand),
    /// Train and evaluate every run of an experiment matrix (the paper's 16 settings x 5 seeds),
    /// then report; or emit the commands for a cluster.
    Sweep(sweep::SweepArgs),
    /// Process role: the replay buffer of a run (started by `ctxrace train`).
    Replay(roles::RoleArgs),
    /// Process role: the learner of a run (started by `ctxrace train`).
    Learner(roles::RoleArgs),
    /// Process role: one actor of a run (started by `ctxrace train`).
    Actor(roles::ActorArgs),
    /// One worker of `ctxrace eval` (started by it).
    #[command(hide = true)]
    EvalWorker(eval::WorkerArgs),
}

/// Where tracks come from and how their raceline is made.
#[derive(Args, Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct TrackArgs {
    /// Folder searched for track names [default: ../shared/tracks if it exists, else .].
    #[arg(long, env = "CTXRACE_TRACKS_DIR", global = true)]
    pub tracks_dir: Option<PathBuf>,
    /// Use the raceline file shipped with the track instead of computing the min-curvature line
    /// (as `[race] shipped_raceline = true`; `train` records it in the run's config).
    #[arg(long, global = true)]
    pub raceline_file: bool,
    /// Raceline speed limit (m/s) [default: 8].
    #[arg(long, global = true)]
    pub v_max: Option<f64>,
    /// Raceline lateral acceleration limit, v²|κ| (m/s²) [default: 5].
    #[arg(long, global = true)]
    pub a_lat: Option<f64>,
    /// Raceline longitudinal acceleration and braking limit (m/s²) [default: 6].
    #[arg(long, global = true)]
    pub a_long: Option<f64>,
}

impl TrackArgs {
    /// The track options these flags describe, with the shipped raceline if `shipped_raceline`
    /// (a race config's choice) or `--raceline-file`.
    pub fn options(&self, shipped_raceline: bool) -> TrackOptions {
        let mut o = TrackOptions::for_race(
            self.tracks_dir.clone(),
            self.raceline_file || shipped_raceline,
        );
        if let Some(v) = self.v_max {
            o.raceline.v_max = v;
        }
        if let Some(v) = self.a_lat {
            o.raceline.a_lat = v;
        }
        if let Some(v) = self.a_long {
            o.raceline.a_long = v;
        }
        o
    }

    /// Loads `spec` (a name, a map yaml, or generated:SEED) for a race with `race`'s raceline
    /// choice.
    pub fn load(&self, spec: &str, race: &RaceConfig) -> Result<Track> {
        Track::load(spec, &self.options(race.shipped_raceline))
            .with_context(|| format!("loading track '{spec}'"))
    }
}

/// Reads a race config TOML (keys it leaves out from its preset), or the defaults.
pub fn load_race_config(path: Option<&PathBuf>) -> Result<RaceConfig> {
    let Some(path) = path else {
        return Ok(RaceConfig::default());
    };
    let text =
        ctxrace_config::config_file::read_config_text(path).context("reading the race config")?;
    RaceConfig::from_toml(&text).map_err(|e| anyhow::anyhow!("race config {}: {e}", path.display()))
}

/// The allocator of every role: mimalloc, told to keep freed memory in the process rather than
/// return it to the kernel. The learner allocates and frees tensors of megabytes every step;
/// returned pages fault in zeroed on the next step. With glibc (even tuned to keep its heap)
/// a `bench learner --algo dreamerv3 --steps 5` run took 152k page faults, with this 1k, and
/// its steps about 4% less time.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// mimalloc's `mi_option_purge_delay` (`mimalloc.h`, the same index in its v2 and v3): the
/// milliseconds before freed memory is returned to the kernel, `-1` for never.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Keeps freed memory for the process's next allocations (see [`ALLOCATOR`]).
fn keep_freed_memory() {
    // SAFETY: mi_option_set only sets an option mimalloc reads when it would purge.
    unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
}

fn main() {
    keep_freed_memory();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Track(c) => track_cmd::run(c),
        Command::Vehicle(a) => vehicle_cmd::run(a),
        Command::Race(a) => race_cmd::run(a),
        Command::Bench(c) => bench::run(c),
        Command::Report(a) => report::run(a),
        Command::Train(a) => train::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Export(c) => export_cmd::run(c),
        Command::Sweep(a) => sweep::run(a),
        Command::EvalWorker(a) => eval::run_worker(a),
        Command::Replay(a) => roles::replay(a),
        Command::Learner(a) => roles::learner(a),
        Command::Actor(a) => roles::actor(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        // a run's process that would fail the same way again tells its launcher so
        let permanent = e.chain().any(|cause| {
            cause.is::<ConfigError>()
                || cause
                    .downcast_ref::<ctxrace_ipc::IpcError>()
                    .is_some_and(ctxrace_ipc::IpcError::is_permanent)
        });
        std::process::exit(if permanent { CONFIG_EXIT_CODE } else { 1 });
    }
}
