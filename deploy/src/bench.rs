//! `ctxrace bench sim`: simulator throughput on one core; `ctxrace bench ipc`: the shared-memory
//! transport against a Unix-socket baseline; `ctxrace bench learner`: see
//! [`crate::bench_learner`].

use crate::TrackArgs;
use anyhow::Result;
use clap::{Args, Subcommand};
use ctxrace_config::Context;
use ctxrace_sim::baseline::{Baseline, BaselineKind};
use ctxrace_sim::RaceEnv;
use serde::Serialize;
use std::sync::Arc;
use std::time::Instant;

/// Benchmarks.
#[derive(Subcommand)]
pub enum BenchCommand {
    /// Decisions/s and physics steps/s of whole races (ego LiDAR, rivals, collisions, resets) on
    /// one core; contexts cycle through the 7 × 7 evaluation grid.
    Sim(SimArgs),
    /// Env steps/s from N actors into replay, batch latency, and the broadcast latency of weights
    /// to M subscribers, over iceoryx2 and over Unix sockets with bincode (the baseline).
    Ipc(IpcArgs),
    /// Gradient steps/s at the paper's batch and acting latency at batch 1 of one algorithm.
    Learner(crate::bench_learner::LearnerArgs),
}

/// Arguments of `ctxrace bench ipc`.
#[derive(Args)]
pub struct IpcArgs {
    /// Actor threads.
    #[arg(long, default_value_t = 4)]
    actors: usize,
    /// Steps each actor sends.
    #[arg(long, default_value_t = 250_000)]
    steps: usize,
    /// Observation size.
    #[arg(long, default_value_t = 108)]
    obs_dim: usize,
    /// Weights size in MiB.
    #[arg(long, default_value_t = 10)]
    weights_mib: usize,
    /// Weights subscribers.
    #[arg(long, default_value_t = 8)]
    subscribers: usize,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Runs `ctxrace bench ipc`.
fn run_ipc(args: IpcArgs) -> Result<()> {
    let opts = crate::bench_ipc::IpcBenchOptions {
        actors: args.actors,
        steps_per_actor: args.steps,
        obs_dim: args.obs_dim,
        weights_bytes: args.weights_mib << 20,
        subscribers: args.subscribers,
        ..Default::default()
    };
    let r = crate::bench_ipc::run_ipc_bench(&opts)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    let (i, u) = (&r.iceoryx2, &r.uds_bincode);
    println!(
        "{} actors x {} steps (obs {}), batches {}x{}, {} MiB weights to {} subscribers",
        opts.actors,
        opts.steps_per_actor,
        opts.obs_dim,
        opts.batch,
        opts.length,
        args.weights_mib,
        opts.subscribers
    );
    println!("                 iceoryx2     uds+bincode   ratio");
    println!(
        "steps/s         {:>10.0}   {:>10.0}   {:>5.1}x {}",
        i.steps_per_sec,
        u.steps_per_sec,
        r.steps_ratio,
        if r.steps_goal_met {
            "(goal >= 1M met)"
        } else {
            "(goal >= 1M NOT met)"
        }
    );
    println!(
        "batch p50/p90   {:>5.2}/{:<5.2}ms {:>5.2}/{:<5.2}ms {:>5.1}x",
        i.batch_ms_p50, i.batch_ms_p90, u.batch_ms_p50, u.batch_ms_p90, r.batch_speedup
    );
    println!(
        "broadcast p50/p90 {:>5.2}/{:<5.2}ms {:>5.2}/{:<5.2}ms {:>5.1}x {}",
        i.broadcast_ms_p50,
        i.broadcast_ms_p90,
        u.broadcast_ms_p50,
        u.broadcast_ms_p90,
        r.broadcast_speedup,
        if r.broadcast_goal_met {
            "(goal < 3 ms met)"
        } else {
            "(goal < 3 ms NOT met)"
        }
    );
    println!(
        "  of which send   {:>5.2} ms      {:>5.2} ms",
        i.broadcast_send_ms_p50, u.broadcast_send_ms_p50
    );
    let one_receive = (i.broadcast_one_ms_p50 - i.broadcast_one_send_ms_p50).max(0.0);
    println!(
        "  floor here      {:>5.2} ms  (to 1 subscriber: send {:.2} ms, receive {:.2} ms; {} \
         receives {} at a time on {} cores)",
        r.broadcast_floor_ms,
        i.broadcast_one_send_ms_p50,
        one_receive,
        opts.subscribers,
        r.cores.min(opts.subscribers),
        r.cores
    );
    Ok(())
}

/// Arguments of `ctxrace bench sim`.
#[derive(Args)]
pub struct SimArgs {
    /// Track name, path to a map yaml, or generated:SEED.
    track: String,
    /// Number of rivals.
    #[arg(long, default_value_t = 3)]
    rivals: usize,
    /// How long to run (s).
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Ego policy while measuring: pure-pursuit, follow-the-gap, random or still.
    #[arg(long, default_value = "pure-pursuit")]
    ego: BaselineKind,
    /// Race config TOML (see configs/race.toml; `[rival] driver` picks the rivals' driver);
    /// --rivals overrides its number of rivals [default: ctxrace's default scenario].
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    tracks: TrackArgs,
}

#[derive(Serialize)]
struct SimReport {
    track: String,
    rivals: usize,
    rival_driver: ctxrace_config::RivalDriverKind,
    ego: String,
    seconds: f64,
    episodes: usize,
    decisions: usize,
    decisions_per_s: f64,
    physics_steps_per_s: f64,
    mean_episode_decisions: f64,
}

/// Runs a benchmark.
pub fn run(cmd: BenchCommand) -> Result<()> {
    let args = match cmd {
        BenchCommand::Sim(args) => args,
        BenchCommand::Ipc(args) => return run_ipc(args),
        BenchCommand::Learner(args) => return crate::bench_learner::run(args),
    };
    if !(args.seconds.is_finite() && args.seconds > 0.0) {
        anyhow::bail!("--seconds {} must be a positive number", args.seconds);
    }
    let cfg = ctxrace_config::RaceConfig {
        rivals: args.rivals,
        ..crate::load_race_config(args.config.as_ref())?
    };
    let rival_driver = cfg.rival.driver;
    let physics_per_decision = cfg.physics_steps_per_action;
    let track = Arc::new(args.tracks.load(&args.track, &cfg)?);
    let mut env = RaceEnv::new(track.clone(), cfg)?;
    let grid = Context::grid(7, 0.3);
    let (mut decisions, mut episodes) = (0usize, 0usize);
    let start = Instant::now();
    while start.elapsed().as_secs_f64() < args.seconds {
        let seed = episodes as u64;
        env.reset(seed, grid[episodes % grid.len()]);
        let mut policy = Baseline::new(args.ego, &env, seed);
        loop {
            let step = env.step(policy.act(&env))?;
            decisions += 1;
            if step.terminated || step.truncated {
                break;
            }
        }
        episodes += 1;
    }
    let secs = start.elapsed().as_secs_f64();
    let r = SimReport {
        track: track.name.clone(),
        rivals: args.rivals,
        rival_driver,
        ego: args.ego.name().into(),
        seconds: secs,
        episodes,
        decisions,
        decisions_per_s: decisions as f64 / secs,
        physics_steps_per_s: (decisions * physics_per_decision) as f64 / secs,
        mean_episode_decisions: decisions as f64 / episodes.max(1) as f64,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "{} · {} {} rivals · ego {} · {:.1} s: {:.0} decisions/s, {:.0} physics steps/s ({} episodes, {:.0} decisions each)",
            r.track, r.rivals, r.rival_driver, r.ego, r.seconds, r.decisions_per_s, r.physics_steps_per_s, r.episodes, r.mean_episode_decisions
        );
    }
    Ok(())
}
