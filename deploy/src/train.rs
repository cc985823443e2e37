//! `ctxrace train`: trains an agent on the simulator. With `--inline` the environment, the
//! replay buffer and the learner share one process and one loop (for development and tests);
//! otherwise the launcher starts the replay, learner and actor processes.
//!
//! A run directory holds `config.toml` (the resolved experiment), `episodes.csv` (one row per
//! training episode: the training curves), `metrics.jsonl` / `metrics.csv` (one row per
//! logging interval of the learner) and `checkpoints/step-*/` (weights, optimiser moments,
//! counters, the acting policy and the agent's configuration).

use crate::lock::DirLock;
use crate::progress::{progress_bar, EpisodeLog, RateMeter};
use crate::results::TrainingEpisode;
use crate::track_check::{check_track, CheckPlan};
use crate::TrackArgs;
use anyhow::{bail, Context as _, Result};
use clap::Args;
use ctxrace_actor::collect::{Collector, Finished};
use ctxrace_actor::RaceEnv;
use ctxrace_common::policy::ACT_DIM;
use ctxrace_common::run_dir::{
    CHECKPOINTS, CONFIG_FILE, METRICS_CSV, METRICS_JSONL, TRAINING_EPISODES,
};
use ctxrace_common::{AlgoKind, ExperimentConfig, Policy, Warmup};
use ctxrace_learner::best::{write_best, ReturnTracker};
use ctxrace_learner::checkpoint::write_checkpoint;
use ctxrace_learner::runlog::MetricsLog;
use ctxrace_learner::Algorithm;
use ctxrace_replay::ReplayBuffer;
use ctxrace_tracks::Track;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

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
    /// newest checkpoint, the replay from its snapshot; an --inline run starts over); start it
    /// if the directory holds no run.
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
    }
    .map_err(anyhow::Error::msg)?;
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
    let actors = if args.inline { 1 } else { args.actors };
    cfg.validate_run(actors).map_err(anyhow::Error::msg)?;
    Ok(cfg)
}

/// Locks the run directory and writes the resolved experiment into it: `--run-dir` (which must
/// not hold a run yet, unless `--resume` and it holds this one), or `runs/<`[`run_name`]`>`
/// (with `--resume` exactly that, otherwise with `-2`, `-3`, … appended when taken). Returns the
/// directory, its lock, and whether it resumes a run.
fn prepare_run_dir(args: &TrainArgs, cfg: &ExperimentConfig) -> Result<(PathBuf, DirLock, bool)> {
    let dir = match &args.run_dir {
        Some(dir) => dir.clone(),
        None if args.resume => PathBuf::from("runs").join(run_name(cfg)),
        None => free_run_dir(cfg)?,
    };
    let lock = DirLock::acquire(&dir)?;
    let config = dir.join(CONFIG_FILE);
    if config.exists() {
        if !args.resume {
            bail!(
                "{} already holds a run; pass another --run-dir, remove it, or continue it \
                 with --resume",
                dir.display()
            );
        }
        let mut held = ExperimentConfig::load_saved(&config).map_err(anyhow::Error::msg)?;
        // the thread count changes how fast a run trains, not what it computes
        held.train.threads = cfg.train.threads;
        if &held != cfg {
            bail!(
                "{} holds another experiment than the one given (compare its {CONFIG_FILE}); \
                 pass another --run-dir",
                dir.display()
            );
        }
    } else if args.resume {
        tracing::info!("{} holds no run yet: starting it", dir.display());
    }
    let resumed = config.exists();
    let text = cfg.to_toml().map_err(anyhow::Error::msg)?;
    ctxrace_common::run_dir::write_atomic(&config, text.as_bytes())
        .with_context(|| format!("writing {}", config.display()))?;
    Ok((dir, lock, resumed))
}

/// `runs/<`[`run_name`]`>`, or the first of its `-2`, `-3`, … variants that holds no run.
fn free_run_dir(cfg: &ExperimentConfig) -> Result<PathBuf> {
    let base = run_name(cfg);
    let taken = |d: &PathBuf| d.join(CONFIG_FILE).exists();
    std::iter::once(PathBuf::from("runs").join(&base))
        .chain((2..10_000).map(|k| PathBuf::from("runs").join(format!("{base}-{k}"))))
        .find(|d| !taken(d))
        .ok_or_else(|| anyhow::anyhow!("runs/{base} and -2 to -9999 are all taken; pass --run-dir"))
}

/// Whether the run in `dir` has taken all its gradient steps (its newest checkpoint is the
/// learner's last).
pub fn is_trained(dir: &Path, cfg: &ExperimentConfig) -> bool {
    let target = ctxrace_learner::process::target_steps(cfg);
    ctxrace_learner::checkpoint::latest_checkpoint(dir)
        .and_then(|c| {
            c.file_name()?
                .to_str()?
                .strip_prefix("step-")?
                .parse::<u64>()
                .ok()
        })
        .is_some_and(|step| step >= target)
}

/// The name of a run: `<algo>-<track>-<rivals>r-s<seed>`, e.g. `cmask-f1_esp-3r-s0`.
pub fn run_name(cfg: &ExperimentConfig) -> String {
    format!(
        "{}-{}-{}r-s{}",
        cfg.agent.algo,
        cfg.track.replace([':', '/'], "_"),
        cfg.race.rivals,
        cfg.train.seed
    )
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
    let cfg = experiment(&args)?;
    // everything a process of the run needs is resolved here, before the run directory is
    // touched: an error it would meet at every restart stops the launch at once
    let track = Arc::new(args.tracks.load(&cfg.track, &cfg.race)?);
    if !args.no_track_check {
        check_training_track(&track, &cfg)?;
    }
    let env = RaceEnv::new(track, cfg.race.clone())?;
    let (dir, lock, resumed) = prepare_run_dir(&args, &cfg)?;
    if resumed && is_trained(&dir, &cfg) {
        println!("{} is trained already", dir.display());
        return Ok(());
    }
    if !args.inline {
        crate::launcher::run(&cfg, &dir, &lock, args.actors, &args.tracks)?;
        let trained = is_trained(&dir, &cfg);
        return finish(&args, &cfg, &dir, trained);
    }
    if resumed {
        // the inline trainer keeps its replay in memory: an interrupted run starts over
        for name in [TRAINING_EPISODES, METRICS_JSONL, METRICS_CSV, CHECKPOINTS] {
            let path = dir.join(name);
            let removed = if path.is_dir() {
                std::fs::remove_dir_all(&path)
            } else {
                std::fs::remove_file(&path)
            };
            match removed {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(e).with_context(|| format!("removing {}", path.display()))
                }
                _ => {}
            }
        }
        eprintln!("{}: the inline run starts over", dir.display());
    }
    run_inline(&cfg, &dir, env)?;
    // the inline run ran to its end (with warm-up by episodes its step count is not known
    // in advance)
    finish(&args, &cfg, &dir, true)
}

/// After a complete run, unless it was resumed (as sweeps do): a first look at what it learned.
fn finish(args: &TrainArgs, cfg: &ExperimentConfig, dir: &Path, trained: bool) -> Result<()> {
    if args.resume || !trained {
        return Ok(());
    }
    crate::first_look::show(cfg, dir, &args.tracks)
}

/// The row of a finished episode.
fn training_episode(f: &Finished, actor: u32, env_steps: u64, grad_steps: u64) -> TrainingEpisode {
    TrainingEpisode {
        env_steps,
        grad_steps,
        actor,
        episode: f.episode,
        context_speed: f.context.speed,
        context_steer: f.context.steer,
        progress: f.metrics.progress,
        overtakes: f.metrics.overtakes,
        a2a: f.metrics.a2a,
        wall_crash: f.metrics.wall_crash,
        episode_return: f.metrics.episode_return,
        steps: f.metrics.steps,
    }
}

/// The single-process trainer: one collector, an in-memory replay buffer and the learner in
/// one loop. After the warm-up (`prefill` random steps, or with `[agent] warmup = "episodes"`
/// `warmup_episodes` episodes of the untrained policy) it keeps the gradient steps at
/// `train_ratio` per env step (with random steps as many in all as
/// [`ctxrace_learner::process::target_steps`]), drawing batches with `[agent] sampler`, reloads
/// the acting policy at the first episode boundary after every `policy_every` gradient steps,
/// logs and checkpoints.
pub fn run_inline(cfg: &ExperimentConfig, dir: &Path, env: RaceEnv) -> Result<()> {
    let t = &cfg.train;
    ctxrace_common::nn::candle_on_one_thread();
    let frame_dim = env.obs_dim();
    let workers = t.threads_for(cfg.agent.algo);
    let mut algo = ctxrace_learner::build(&cfg.agent, frame_dim, workers)?;
    let mut policy = Policy::new(&cfg.agent, frame_dim, &algo.policy_weights()?, t.seed)?;
    let mut collector = Collector::new(env, t.context_range, t.seed)
        .with_paper_code_rows(cfg.agent.stores_paper_code_rows());
    let mut buffer = ReplayBuffer::new(cfg.replay.capacity, 1, frame_dim, ACT_DIM);
    let mut rng = ChaCha8Rng::seed_from_u64(t.seed ^ 0x7265_706c_6179);
    let spec = cfg.agent.batch_spec();
    let mut episodes = EpisodeLog::open(dir, "inline")?;
    let mut metrics_log = MetricsLog::open(dir, "inline-learner")?;
    let mut meter = RateMeter::default();
    let bar = progress_bar(t.env_steps, "env steps");
    let start = Instant::now();
    let (mut stale_policy, mut recent) = (false, Vec::<f64>::new());
    let mut payload = Vec::new();
    let mut tracker = ReturnTracker::default();
    let mut trained_after = None;
    while collector.decisions() < t.env_steps {
        payload.clear();
        let by_policy = cfg.acts_by_policy(collector.decisions());
        let acting = if by_policy { Some(&mut policy) } else { None };
        let finished = collector.step(acting, |s| s.encode(&mut payload))?;
        buffer.insert_chunk(0, &payload, false);
        bar.inc(1);
        if let Some(f) = finished {
            let row = training_episode(&f, 0, collector.decisions(), algo.steps());
            episodes.write(&row)?;
            recent.push(row.progress);
            if recent.len() > 10 {
                recent.remove(0);
            }
            if f.by_policy && tracker.observe(f.metrics.episode_return) {
                write_best(dir, algo.as_ref(), &cfg.agent, &tracker)?;
            }
        }
        if trained_after.is_none() {
            trained_after = cfg.warmup_end(collector.decisions(), collector.episodes());
        }
        if let Some(after) = trained_after {
            let due = ((collector.decisions() - after) as f64 * t.train_ratio).round() as u64;
            while algo.steps() < due {
                let Some(batch) = buffer.sample(spec, cfg.agent.sampler, &mut rng) else {
                    break;
                };
                let mut m = algo.train_step(&batch)?;
                let steps = algo.steps();
                stale_policy |= steps.is_multiple_of(t.policy_every);
                if steps.is_multiple_of(t.log_every) {
                    m.insert("grad_steps".into(), steps as f64);
                    m.insert("env_steps".into(), collector.decisions() as f64);
                    m.insert("seconds".into(), start.elapsed().as_secs_f64());
                    metrics_log.write(&m)?;
                }
                if t.checkpoint_every > 0 && steps.is_multiple_of(t.checkpoint_every) {
                    write_checkpoint(dir, algo.as_ref(), &cfg.agent, &tracker)?;
                }
            }
            if stale_policy && collector.at_episode_boundary() {
                policy.load(&algo.policy_weights()?)?;
                stale_policy = false;
            }
        }
        if collector.decisions().is_multiple_of(50) {
            bar.set_message(status(algo.as_ref(), &recent, collector.episodes(), &start));
            let held = (buffer.len() as u64, buffer.capacity() as u64);
            if let Some(rates) = meter.read(collector.decisions(), algo.steps(), held) {
                episodes.rates(collector.decisions(), &rates)?;
            }
        }
    }
    let last = write_checkpoint(dir, algo.as_ref(), &cfg.agent, &tracker)?;
    bar.finish_with_message(status(algo.as_ref(), &recent, collector.episodes(), &start));
    println!(
        "trained {} for {} env steps and {} gradient steps in {:.0} s; checkpoint {}",
        cfg.agent.algo,
        collector.decisions(),
        algo.steps(),
        start.elapsed().as_secs_f64(),
        last.display()
    );
    Ok(())
}

/// The progress bar's message: gradient steps and their rate, episodes, recent progress.
fn status(algo: &dyn Algorithm, recent: &[f64], episodes: u64, start: &Instant) -> String {
    let mean = if recent.is_empty() {
        0.0
    } else {
        recent.iter().sum::<f64>() / recent.len() as f64
    };
    format!(
        "| {} grad steps ({:.1}/s) | {episodes} episodes | progress {mean:.3} (last 10)",
        algo.steps(),
        algo.steps() as f64 / start.elapsed().as_secs_f64().max(1e-9)
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_common::{AgentConfig, DreamerConfig, RaceConfig};
    use ctxrace_tracks::{Track, TrackOptions};

    #[test]
    fn run_names_carry_every_axis_of_the_paper_matrix() {
        let mut cfg = ExperimentConfig::default();
        cfg.race.rivals = 3;
        cfg.train.seed = 4;
        assert_eq!(run_name(&cfg), "dreamerv3-f1_esp-3r-s4");
        cfg.track = "generated:7".into();
        cfg.agent.algo = AlgoKind::Sac;
        cfg.race.rivals = 1;
        assert_eq!(run_name(&cfg), "sac-generated_7-1r-s4");
    }

    #[test]
    fn the_world_model_learns_recorded_race_data() {
        ctxrace_common::nn::candle_on_one_thread();
        // 2000 decisions of a random ego against one rival on a generated circuit
        let track = Arc::new(Track::load("generated:0", &TrackOptions::default()).unwrap());
        let race = RaceConfig {
            rivals: 1,
            ..RaceConfig::default()
        };
        let env = RaceEnv::new(track, race).unwrap();
        let frame_dim = env.obs_dim();
        let mut collector = Collector::new(env, 0.15, 1);
        let mut buffer = ReplayBuffer::new(10_000, 1, frame_dim, ACT_DIM);
        let mut payload = Vec::new();
        while collector.decisions() < 2000 {
            payload.clear();
            collector.step(None, |s| s.encode(&mut payload)).unwrap();
            buffer.insert_chunk(0, &payload, false);
        }
        let agent = AgentConfig {
            algo: AlgoKind::Dreamerv3,
            dreamer: DreamerConfig {
                units: 64,
                layers: 2,
                deter: 64,
                hidden: 64,
                stoch: 8,
                classes: 8,
                head_units: 64,
                head_layers: 2,
                batch: 8,
                length: 16,
                model_lr: 1e-3,
                ..DreamerConfig::default()
            },
            ..AgentConfig::default()
        };
        let mut algo = ctxrace_learner::build(&agent, frame_dim, 1).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut history = Vec::new();
        for _ in 0..150 {
            let batch = buffer
                .sample(agent.batch_spec(), agent.sampler, &mut rng)
                .unwrap();
            let m = algo.train_step(&batch).unwrap();
            history.push((m["model/recon"], m["model/reward"]));
        }
        let mean = |xs: &[(f64, f64)]| {
            let n = xs.len() as f64;
            let sum = xs.iter().fold((0.0, 0.0), |s, x| (s.0 + x.0, s.1 + x.1));
            (sum.0 / n, sum.1 / n)
        };
        let ((recon0, reward0), (recon1, reward1)) = (mean(&history[..10]), mean(&history[140..]));
        eprintln!("recon {recon0:.3} -> {recon1:.3}, reward {reward0:.3} -> {reward1:.3}");
        assert!(recon1 < 0.5 * recon0, "recon {recon0} -> {recon1}");
        assert!(reward1 < 0.5 * reward0, "reward {reward0} -> {reward1}");
    }
}
