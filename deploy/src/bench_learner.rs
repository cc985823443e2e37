//! `ctxrace bench learner`: gradient steps per second at the paper's batch (16 × 64 sequences;
//! SAC 100 transitions of two stacked frames) and the acting latency at batch 1, for one
//! algorithm, on batches of random data of the racing shapes (108 beams, 2 actions).

use anyhow::Result;
use clap::Args;
use ctxrace_common::batch::{Batch, BatchSpec};
use ctxrace_common::policy::ACT_DIM;
use ctxrace_common::{
    AgentConfig, AlgoKind, ExperimentConfig, Policy, SequenceBatch, TransitionBatch,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `ctxrace bench learner`.
#[derive(Args)]
pub struct LearnerArgs {
    /// Algorithm.
    #[arg(long, default_value = "cmask")]
    algo: AlgoKind,
    /// Experiment TOML whose `[agent]` to use [default: the paper's hyper-parameters].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Timed gradient steps (after one untimed warm-up step).
    #[arg(long, default_value_t = 5)]
    steps: usize,
    /// Timed acting steps at batch 1.
    #[arg(long, default_value_t = 500)]
    act_steps: usize,
    /// Worker threads while training (acting always uses one) [default: 1 for SAC, 2 for the
    /// DreamerV3 variants, which split each batch over them].
    #[arg(long)]
    threads: Option<usize>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// The figures of one run.
#[derive(Serialize)]
struct LearnerReport {
    algo: String,
    batch: String,
    threads: usize,
    seconds_per_step: f64,
    steps_per_second: f64,
    act_ms_mean: f64,
    act_ms_p50: f64,
    act_ms_p90: f64,
}

/// A batch of `spec` with random contents of the racing shapes.
fn random_batch(spec: BatchSpec, beams: usize, rng: &mut ChaCha8Rng) -> Batch {
    let mut v = |n: usize, lo: f32, hi: f32| {
        (0..n)
            .map(|_| rng.random_range(lo..hi))
            .collect::<Vec<f32>>()
    };
    match spec {
        BatchSpec::Sequence { batch, length } => {
            let n = batch * length;
            let is_first: Vec<f32> = (0..n)
                .map(|i| f32::from(i.is_multiple_of(length)))
                .collect();
            let has_mask = is_first.iter().map(|f| 1.0 - f).collect();
            Batch::Sequence(SequenceBatch {
                batch,
                length,
                obs_dim: beams,
                act_dim: ACT_DIM,
                obs: v(n * beams, 0.0, 1.0),
                action: v(n * ACT_DIM, -1.0, 1.0),
                reward: v(n, -1.0, 1.0),
                is_first,
                is_terminal: vec![0.0; n],
                context: v(n * 2, -0.15, 0.15),
                mask: v(n * 2, 0.0, 1.0),
                has_mask,
            })
        }
        BatchSpec::Transition { batch, frames } => Batch::Transition(TransitionBatch {
            batch,
            obs_dim: beams * frames,
            act_dim: ACT_DIM,
            obs: v(batch * beams * frames, 0.0, 1.0),
            action: v(batch * ACT_DIM, -1.0, 1.0),
            reward: v(batch, -1.0, 1.0),
            next_obs: v(batch * beams * frames, 0.0, 1.0),
            terminal: vec![0.0; batch],
            context: v(batch * 2, -0.15, 0.15),
        }),
    }
}

/// Runs `ctxrace bench learner`.
pub fn run(args: LearnerArgs) -> Result<()> {
    let mut agent: AgentConfig = match &args.config {
        Some(path) => {
            ExperimentConfig::load(path)
                .map_err(anyhow::Error::msg)?
                .agent
        }
        None => AgentConfig::default(),
    };
    agent.algo = args.algo;
    let beams = ctxrace_common::LidarConfig::default().beams;
    let spec = agent.batch_spec();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = random_batch(spec, beams, &mut rng);

    let threads = args.threads.unwrap_or(agent.algo.learner_threads());
    ctxrace_common::nn::set_threads(threads);
    let mut algo = ctxrace_learner::build(&agent, beams)?;
    algo.train_step(&batch)?;
    let start = Instant::now();
    for _ in 0..args.steps.max(1) {
        algo.train_step(&batch)?;
    }
    let per_step = start.elapsed().as_secs_f64() / args.steps.max(1) as f64;

    ctxrace_common::nn::set_threads(1);
    let mut policy = Policy::new(&agent, beams, &algo.policy_weights()?, 0)?;
    let obs: Vec<f32> = (0..beams).map(|_| rng.random_range(0.0..1.0)).collect();
    let mut times = Vec::with_capacity(args.act_steps);
    for _ in 0..args.act_steps.max(1) {
        let t = Instant::now();
        policy.act(&obs, [0.1, -0.1], false)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    let pct = |q: f64| times[((times.len() - 1) as f64 * q).round() as usize];
    let report = LearnerReport {
        algo: agent.algo.to_string(),
        batch: match spec {
            BatchSpec::Sequence { batch, length } => format!("{batch} x {length} sequences"),
            BatchSpec::Transition { batch, frames } => {
                format!("{batch} transitions x {frames} frames")
            }
        },
        threads,
        seconds_per_step: per_step,
        steps_per_second: 1.0 / per_step,
        act_ms_mean: times.iter().sum::<f64>() / times.len() as f64,
        act_ms_p50: pct(0.5),
        act_ms_p90: pct(0.9),
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{} ({}, {} threads): {:.2} ms per gradient step ({:.2} steps/s); acting at batch 1: \
             mean {:.3} ms, p50 {:.3} ms, p90 {:.3} ms",
            report.algo,
            report.batch,
            report.threads,
            report.seconds_per_step * 1e3,
            report.steps_per_second,
            report.act_ms_mean,
            report.act_ms_p50,
            report.act_ms_p90
        );
    }
    Ok(())
}
