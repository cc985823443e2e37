//! `ctxrace train`: trains an agent on the simulator. With `--inline` the environment, the
//! replay buffer and the learner share one process and one loop (for development and tests);
//! otherwise the launcher starts the replay, learner and actor processes.
//!
//! A run directory holds `config.toml` (the resolved experiment), `episodes.csv` (one row per
//! training episode: the training curves), `metrics.jsonl` / `metrics.csv` (one row per
//! logging interval of the learner) and `checkpoints/step-*/` (weights, optimiser moments,
//! counters, the acting policy and the agent's configuration).

use crate::progress::progress_bar;
use crate::TrackArgs;
use anyhow::{bail, Result};
use clap::Args;
use ctxrace_actor::collect::Collector;
use ctxrace_config::resources::{check_machine, Machine};
use ctxrace_config::{AlgoKind, ExperimentConfig, Warmup};
use ctxrace_learner::inline::InlineProgress;
use ctxrace_learner::process::is_trained;
use ctxrace_nn::policy::ACT_DIM;
use ctxrace_replay::ReplayBuffer;
use ctxrace_run::run_folder::RunFolder;
use ctxrace_sim::track_check::{check_track, CheckPlan};
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::Track;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The experiment `ctxrace train` runs without a CONFIG argument (configs/quick.toml).
pub const EMBEDDED_CONFIG: &str = include_str!("../../configs/quick.toml");

/// Arguments of `ctxrace train`.
#[derive(Args)]
pub struct TrainArgs {
    /// Experiment TOML (see configs/) [default: the embedded configs/quick.toml].
    config: Option<PathBuf>,
    /// Run environment, replay and learner in this process (no shared memory, one actor).
    #[arg(long)]
    inline: bool,
    /// Actor processes (without --inline).
    #[arg(long, default_value_t = 2)]
    actors: usize,
    /// Run more actor processes than 4 a core (refused otherwise: they mostly wait).
    #[arg(long)]
    oversubscribe: bool,
    /// Algorithm: sac, dreamerv3, crssm or cmask [default: the config's].
    #[arg(long)]
    algo: Option<AlgoKind>,
    /// Track: a name in the tracks folder, a map yaml or generated:SEED [default: the config's].
    #[arg(long)]
    track: Option<String>,
    /// Number of rivals, 0 to 7 [default: the config's].
    #[arg(long)]
    rivals: Option<usize>,
    /// Environment steps [default: the config's].
    #[arg(long)]
    steps: Option<u64>,
    /// Seed [default: the config's].
    #[arg(long)]
    seed: Option<u64>,
    /// Run directory [default: runs/<algo>-<track>-<rivals>r-s<seed>].
    #[arg(long)]
    run_dir: Option<PathBuf>,
    /// Continue the run in the run directory if it holds this experiment (the learner from its
    /// newest checkpoint, the replay from its snapshot; an --inline run from its resume point,
    /// exactly); start it if the directory holds no run.
    #[arg(long)]
    resume: bool,
    /// Learner worker threads [default: the config's, else the algorithm's].
    #[arg(long)]
    threads: Option<usize>,
    /// Train even where `ctxrace track check` finds that rivals crash on their own in the
    /// training contexts.
    #[arg(long)]
    no_track_check: bool,
    #[command(flatten)]
    tracks: TrackArgs,
}

/// Reads the experiment and applies the command-line overrides.
fn experiment(args: &TrainArgs) -> Result<ExperimentConfig> {
    let mut cfg = match &args.config {
        Some(path) => ExperimentConfig::load(path),
        None => ExperimentConfig::from_toml(EMBEDDED_CONFIG, "embedded configs/quick.toml"),
    }?;
    if let Some(algo) = args.algo {
        cfg.agent.algo = algo;
    }
    if let Some(track) = &args.track {
        cfg.track = track.clone();
    }
    if let Some(rivals) = args.rivals {
        cfg.race.rivals = rivals;
    }
    if let Some(steps) = args.steps {
        cfg.train.env_steps = steps;
    }
    if let Some(seed) = args.seed {
        cfg.train.seed = seed;
    }
    if args.threads.is_some() {
        cfg.train.threads = args.threads;
    }
    cfg.race.shipped_raceline |= args.tracks.raceline_file;
    cfg.agent.set_seed(cfg.train.seed);
    if !args.inline && args.actors == 0 {
        bail!("--actors = 0: a run needs at least 1 actor process; pass --actors 1 or more");
    }
    if !args.inline && cfg.agent.warmup == Warmup::Episodes {
        bail!(
            "[agent] warmup = \"episodes\" runs only in the single-process trainer: pass \
             --inline, or set warmup = \"random-steps\" (with [train] prefill) for a run of \
             actor processes"
        );
    }
    if !args.inline && !cfg.train.keep_best_at.is_empty() {
        bail!(
            "[train] keep_best_at is kept by the single-process trainer only (it knows each env \
             step): pass --inline, or leave keep_best_at out for a run of actor processes"
        );
    }
    let actors = if args.inline { 1 } else { args.actors };
    cfg.validate_run(actors)?;
    Ok(cfg)
}

/// Refuses a map on which rivals cannot drive the training contexts (they would crash on their
/// own in the episodes the agent learns from); other failing checks of `track check` are
/// warnings. Checked over a 7 × 7 grid of the training contexts, from every grid place.
fn check_training_track(track: &Arc<Track>, cfg: &ExperimentConfig) -> Result<()> {
    let plan = CheckPlan {
        grid: 7,
        range: cfg.train.context_range,
        places: cfg.race.rivals,
    };
    let report = check_track(track.clone(), &cfg.race, plan)?;
    let failures: Vec<String> = report
        .failures()
        .map(|f| format!("  {}: {}", f.check, f.detail))
        .collect();
    if report.rivals_fail() {
        // the first few races that failed, then the rivals' summary (the last finding)
        const SHOWN: usize = 5;
        let mut failures = failures;
        if failures.len() > SHOWN + 1 {
            let more = failures.len() - SHOWN - 1;
            failures.splice(
                SHOWN..failures.len() - 1,
                [format!("  ... and {more} more")],
            );
        }
        bail!(
            "{} is not raceable in the training contexts (|c| <= {}, {} rival(s)):\n{}\nchoose \
             another track, fewer rivals or a narrower train.context_range, see `ctxrace track \
             check {}`, or pass --no-track-check to train on it anyway",
            track.name,
            cfg.train.context_range,
            cfg.race.rivals,
            failures.join("\n"),
            track.name
        );
    }
    for line in failures {
        eprintln!("warning: {}{line}", track.name);
    }
    Ok(())
}

/// Runs `ctxrace train`.
pub fn run(args: TrainArgs) -> Result<()> {
    // paths the run's processes and files name: refused before anything is read or made
    let paths = [
        ("the config", args.config.as_deref()),
        ("--run-dir", args.run_dir.as_deref()),
        ("--tracks-dir", args.tracks.tracks_dir.as_deref()),
    ];
    for (what, path) in paths {
        if let Some(p) = path.filter(|p| p.to_str().is_none()) {
            bail!(
                "{what} {} is not valid UTF-8: a run names its folder and config in its files, \
                 logs and process command lines; rename it or choose another",
                p.display()
            );
        }
    }
    let cfg = experiment(&args)?;
    let actors = if args.inline { 1 } else { args.actors };
    // everything a process of the run needs is resolved here, before the run directory is
    // touched: an error it would meet at every restart stops the launch at once
    let track = Arc::new(args.tracks.load(&cfg.track, &cfg.race)?);
    let map_pixels = track
        .map
        .as_ref()
        .map_or(0, |m| (m.width * m.height) as u64);
    check_machine(
        &cfg,
        actors,
        map_pixels,
        &Machine::this(),
        args.oversubscribe,
    )?;
    if !args.no_track_check {
        check_training_track(&track, &cfg)?;
    }
    let env = RaceEnv::new(track, cfg.race.clone())?;
    let run = RunFolder::prepare(&cfg, args.run_dir.as_deref(), args.resume)?;
    if !run.resumed && args.resume {
        tracing::info!("{} holds no run yet: starting it", run.dir.display());
    }
    let dir = run.dir.as_path();
    if run.resumed && is_trained(dir, &cfg) {
        println!("{} is trained already", dir.display());
        return Ok(());
    }
    if !args.inline {
        crate::roles::check_replay_snapshot(&cfg, dir, args.actors)?;
        crate::launcher::run(&cfg, dir, &run.lock, args.actors, &args.tracks)?;
        let trained = is_trained(dir, &cfg);
        return finish(&args, &cfg, dir, trained);
    }
    if run.resumed {
        match ctxrace_learner::resume::find(dir) {
            Ok(Some(point)) => eprintln!(
                "{}: the inline run continues from its resume point at {} env steps",
                dir.display(),
                point.state.source.decisions
            ),
            found => {
                let why = match found {
                    Err(e) => format!("its resume point is unusable ({e})"),
                    _ => "it has no resume point".to_string(),
                };
                run.start_over()?;
                eprintln!("{}: the inline run starts over: {why}", dir.display());
            }
        }
    }
    train_inline(&cfg, dir, env)?;
    // the inline run ran to its end (with warm-up by episodes its step count is not known
    // in advance)
    finish(&args, &cfg, dir, true)
}

/// After a complete run, unless it was resumed (as sweeps do): a first look at what it learned.
fn finish(args: &TrainArgs, cfg: &ExperimentConfig, dir: &Path, trained: bool) -> Result<()> {
    if args.resume || !trained {
        return Ok(());
    }
    crate::first_look::show(cfg, dir, &args.tracks)
}

/// Runs the single-process trainer ([`ctxrace_learner::inline`]) on `env`'s collector and an
/// in-memory replay buffer with a progress bar, and says what it did.
fn train_inline(cfg: &ExperimentConfig, dir: &Path, env: RaceEnv) -> Result<()> {
    let plan = cfg.plan();
    let bar = progress_bar(plan.env_steps, "env steps");
    let frame_dim = env.obs_dim();
    let mut collector = Collector::for_experiment(env, cfg, cfg.train.seed);
    let mut buffer = ReplayBuffer::new(plan.replay.capacity, 1, frame_dim, ACT_DIM);
    let run = ctxrace_learner::inline::run_inline(cfg, dir, &mut collector, &mut buffer, |p| {
        bar.set_position(p.decisions);
        if p.decisions.is_multiple_of(50) {
            bar.set_message(status(p));
        }
    })?;
    bar.finish_with_message(status(&run.progress));
    println!(
        "trained {} for {} env steps and {} gradient steps in {:.0} s; checkpoint {}",
        cfg.agent.algo,
        run.progress.decisions,
        run.progress.grad_steps,
        run.progress.elapsed.as_secs_f64(),
        run.checkpoint.display()
    );
    Ok(())
}

/// The progress bar's message: gradient steps and their rate, episodes, recent progress.
fn status(p: &InlineProgress) -> String {
    format!(
        "| {} grad steps ({:.1}/s) | {} episodes | progress {:.3} (last 10)",
        p.grad_steps,
        p.grad_steps as f64 / p.elapsed.as_secs_f64().max(1e-9),
        p.episodes,
        p.recent_progress
    )
}
