//! `ctxrace bench learner`: gradient steps per second at the paper's batch (16 × 64 sequences;
//! SAC 100 transitions of two stacked frames) and the acting latency at batch 1, for one
//! algorithm, on batches of random data of the racing shapes (108 beams, 2 actions).
//!
//! **Fraction of peak.** The floating-point operations of a step are those of the linear layers'
//! matrix products (forward and backward, `2 m n k` each), counted as they run
//! ([`ctxrace_common::nn::kernels::matmul_flops`]), per phase for the DreamerV3 variants (world
//! model; behaviour: imagination, actor and critic; cMask's mask SAC). Elementwise work is not
//! counted, so the fraction is a lower bound of the arithmetic done. The peak is
//! `threads × 2 FMA units × lanes × 2 flops × clock`, with 16 lanes for AVX-512, 8 for AVX2 with
//! FMA (4 otherwise) and the highest of the clocks the kernel reports (cpufreq's maximum when it
//! exposes one, `/proc/cpuinfo`'s "cpu MHz") and the clock measured on a busy core: a virtual
//! machine's "cpu MHz" is often the nominal clock while its cores boost above it, which would
//! put the fraction too high (on an EPYC 7002 guest one core's gemm ran at 84 GFLOP/s against a
//! 72 GFLOP/s "peak" of the reported 2.25 GHz).

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
    /// Mean, fastest and median seconds of the timed steps.
    seconds_per_step: f64,
    seconds_min: f64,
    seconds_median: f64,
    steps_per_second: f64,
    act_ms_mean: f64,
    act_ms_p50: f64,
    act_ms_p90: f64,
    /// Matrix-product GFLOP of one step, in all and by phase.
    gflop_per_step: f64,
    gflop_by_phase: Vec<(String, f64)>,
    /// Wall seconds of each phase of the last step (DreamerV3 variants).
    seconds_by_phase: Vec<(String, f64)>,
    /// Achieved GFLOP/s of the matrix products.
    gflops: f64,
    /// The peak GFLOP/s of `threads` cores and how it was computed.
    peak_gflops: f64,
    peak_from: String,
    /// `gflops / peak_gflops`.
    fraction_of_peak: f64,
}

/// The peak f32 GFLOP/s of `threads` cores (see the module doc), with how it was computed.
fn peak_gflops(threads: usize) -> (f64, String) {
    let lanes = if std::is_x86_feature_detected!("avx512f") {
        16
    } else if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        8
    } else {
        4
    };
    let cpufreq = std::fs::read_to_string("/sys/devices/system/cpu/cpu0/cpufreq/cpuinfo_max_freq")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .map(|khz| (khz / 1e6, "cpufreq maximum"));
    let cpuinfo = || {
        std::fs::read_to_string("/proc/cpuinfo")
            .ok()?
            .lines()
            .find(|l| l.starts_with("cpu MHz"))?
            .split(':')
            .nth(1)?
            .trim()
            .parse::<f64>()
            .ok()
            .map(|mhz| (mhz / 1e3, "/proc/cpuinfo"))
    };
    let (ghz, source) = [cpufreq, cpuinfo(), measured_ghz().map(|g| (g, "measured"))]
        .into_iter()
        .flatten()
        .fold(
            (0.0, "no clock found"),
            |best, c| if c.0 > best.0 { c } else { best },
        );
    let peak = threads as f64 * 2.0 * lanes as f64 * 2.0 * ghz;
    (
        peak,
        format!("{threads} cores x 2 FMA x {lanes} lanes x 2 flops x {ghz:.2} GHz ({source})"),
    )
}

/// The clock of a busy core in GHz, timed on a chain of dependent register additions (one
/// cycle each on every x86 core: an addition's latency is one cycle, and an addition of two
/// registers is not folded away at rename as some cores do with immediates), the fastest of
/// three runs of a tenth of a second or so.
#[cfg(target_arch = "x86_64")]
fn measured_ghz() -> Option<f64> {
    const ITERATIONS: u64 = 25_000_000; // of 8 additions each
    let seconds = (0..3)
        .map(|_| {
            let started = Instant::now();
            let (mut x, one, mut n) = (0u64, 1u64, ITERATIONS);
            // SAFETY: register arithmetic only; no memory is read or written.
            unsafe {
                std::arch::asm!(
                    "2:",
                    "add {x}, {one}", "add {x}, {one}", "add {x}, {one}", "add {x}, {one}",
                    "add {x}, {one}", "add {x}, {one}", "add {x}, {one}", "add {x}, {one}",
                    "dec {n}",
                    "jnz 2b",
                    x = inout(reg) x,
                    one = in(reg) one,
                    n = inout(reg) n,
                    options(nomem, nostack),
                );
            }
            std::hint::black_box((x, n));
            started.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min);
    (seconds > 0.0).then(|| 8.0 * ITERATIONS as f64 / seconds / 1e9)
}

/// No measured clock off x86.
#[cfg(not(target_arch = "x86_64"))]
fn measured_ghz() -> Option<f64> {
    None
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
    let flops_before = ctxrace_common::nn::kernels::matmul_flops();
    let mut metrics = Default::default();
    let mut step_times = Vec::with_capacity(args.steps.max(1));
    for _ in 0..args.steps.max(1) {
        let t = Instant::now();
        metrics = algo.train_step(&batch)?;
        step_times.push(t.elapsed().as_secs_f64());
    }
    let per_step = step_times.iter().sum::<f64>() / step_times.len() as f64;
    step_times.sort_by(f64::total_cmp);
    let by_phase = |prefix: &str, scale: f64| -> Vec<(String, f64)> {
        metrics
            .iter()
            .filter_map(|(k, v)| Some((k.strip_prefix(prefix)?.to_string(), v * scale)))
            .collect()
    };
    let flops = ctxrace_common::nn::kernels::matmul_flops() - flops_before;
    let gflop_per_step = flops as f64 / args.steps.max(1) as f64 / 1e9;
    let gflop_by_phase = by_phase("flops/", 1e-9);
    let seconds_by_phase = by_phase("seconds/", 1.0);
    let (peak, peak_from) = peak_gflops(threads);
    let gflops = gflop_per_step / per_step;

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
        seconds_min: step_times[0],
        seconds_median: step_times[step_times.len() / 2],
        steps_per_second: 1.0 / per_step,
        act_ms_mean: times.iter().sum::<f64>() / times.len() as f64,
        act_ms_p50: pct(0.5),
        act_ms_p90: pct(0.9),
        gflop_per_step,
        gflop_by_phase,
        seconds_by_phase,
        gflops,
        peak_gflops: peak,
        peak_from,
        fraction_of_peak: if peak > 0.0 { gflops / peak } else { 0.0 },
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{} ({}, {} threads): {:.2} ms per gradient step ({:.2} steps/s; fastest {:.2} ms, \
             median {:.2} ms); acting at batch 1: mean {:.3} ms, p50 {:.3} ms, p90 {:.3} ms",
            report.algo,
            report.batch,
            report.threads,
            report.seconds_per_step * 1e3,
            report.steps_per_second,
            report.seconds_min * 1e3,
            report.seconds_median * 1e3,
            report.act_ms_mean,
            report.act_ms_p50,
            report.act_ms_p90
        );
        let phases: Vec<String> = report
            .gflop_by_phase
            .iter()
            .map(|(phase, g)| format!("{phase} {g:.2}"))
            .collect();
        println!(
            "  matrix products: {:.2} GFLOP per step ({}), {:.1} GFLOP/s = {:.1}% of the peak \
             {:.1} GFLOP/s ({})",
            report.gflop_per_step,
            phases.join(", "),
            report.gflops,
            100.0 * report.fraction_of_peak,
            report.peak_gflops,
            report.peak_from
        );
        let gflop_of = |phase: &str| {
            let found = report.gflop_by_phase.iter().find(|(p, _)| p == phase);
            found.map_or(0.0, |(_, g)| *g)
        };
        let phases: Vec<String> = report
            .seconds_by_phase
            .iter()
            .map(|(phase, s)| {
                let rate = gflop_of(phase) / s.max(1e-12);
                format!("{phase} {:.1} ms ({rate:.1} GFLOP/s)", s * 1e3)
            })
            .collect();
        if !phases.is_empty() {
            println!("  last step by phase: {}", phases.join(", "));
        }
    }
    Ok(())
}
