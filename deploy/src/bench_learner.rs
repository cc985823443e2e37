//! `ctxrace bench learner`: gradient steps per second at the paper's batch (16 × 64 sequences;
//! SAC 100 transitions of two stacked frames) and the acting latency at batch 1, for one
//! algorithm, on batches of random data of the racing shapes (108 beams, 2 actions).
//!
//! **Fraction of peak.** The floating-point operations of a step are those of the linear layers'
//! matrix products (forward and backward, `2 m n k` each), counted as they run
//! ([`ctxrace_nn::kernels::matmul_flops`]), per phase for the DreamerV3 variants (world
//! model; imagination: the rollouts, heads and returns; actor_critic: the backward pass to the
//! actor's and critic's gradients and their steps; cMask's mask SAC). Elementwise work is not
//! counted, so the fraction is a lower bound of the arithmetic done. The peak is `threads` times
//! one core's rate of fused multiply-adds measured on the widest vectors the kernels use (AVX-512
//! in a build with the `avx512` feature, else AVX2 with FMA): independent chains of register
//! FMAs, enough to cover their latency, timed on a busy core.
//! It is a measurement, not `2 FMA units × lanes × clock` from the feature flags, because cores
//! differ in what they do with a wide instruction: an AMD Zen 4 has AVX-512 but runs each 512-bit
//! FMA as two 256-bit halves, so its peak is half of what its flags suggest (32, not 64, flops a
//! cycle), while an Intel Xeon with two 512-bit units reaches 64. The clock is measured too (a
//! chain of dependent register additions), to show flops per cycle; a virtual machine's
//! `/proc/cpuinfo` often reports the nominal clock while its busy cores boost above it. Without
//! an FMA probe (off x86, or no FMA) the peak falls back to `2 units × 4 lanes × 2 × clock`.
//!
//! **The products' ceiling.** One more step runs with its gemm calls recorded by shape and
//! strides; the same calls then run again alone on one core, on operands reused from call to call
//! ([`ctxrace_nn::kernels::rerun_products`]; the fastest of three reruns). Their rate
//! is what this machine's gemm reaches on the step's shapes with nothing in the way, an upper
//! bound for the step; their time spread over the step's threads, as a share of the step's, is
//! how much of the step the products explain (the rest: the row kernels, the one-hot products,
//! copies, cold operands, waiting threads).
use anyhow::Result;
use clap::Args;
use ctxrace_config::batch::{Batch, BatchSpec};
use ctxrace_config::{AgentConfig, AlgoKind, ExperimentConfig, SequenceBatch, TransitionBatch};
use ctxrace_nn::policy::ACT_DIM;
use ctxrace_nn::Policy;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::collections::BTreeMap;
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
    /// Median wall seconds of each phase over the timed steps (DreamerV3 variants).
    seconds_by_phase: Vec<(String, f64)>,
    /// Achieved GFLOP/s of the matrix products.
    gflops: f64,
    /// The peak GFLOP/s of `threads` cores and how it was computed.
    peak_gflops: f64,
    peak_from: String,
    /// `gflops / peak_gflops`.
    fraction_of_peak: f64,
    /// The products' ceiling: one step's gemm calls replayed alone on one core (see the module
    /// doc): their number, GFLOP, seconds, GFLOP/s and fraction of one core's peak.
    products_alone: ProductsAlone,
}

/// One step's gemm calls run again alone on one core
/// ([`ctxrace_nn::kernels::rerun_products`]).
#[derive(Serialize)]
struct ProductsAlone {
    calls: usize,
    gflop: f64,
    seconds: f64,
    gflops: f64,
    fraction_of_core_peak: f64,
    /// The step's time if it were these products alone, spread evenly over its threads, as a
    /// fraction of its measured time: how much of the step the products explain.
    share_of_step: f64,
}

/// Records the gemm calls of one more step of `algo` and runs them again alone on this thread,
/// keeping the fastest of three reruns.
fn products_alone(
    algo: &mut dyn ctxrace_learner::Algorithm,
    batch: &Batch,
    (threads, core_peak, per_step): (usize, f64, f64),
) -> Result<ProductsAlone> {
    use ctxrace_nn::kernels::{record_products, recorded_products, rerun_products};
    record_products(true);
    let stepped = algo.train_step(batch);
    record_products(false);
    stepped?;
    let calls = recorded_products();
    let seconds = (0..3)
        .map(|_| rerun_products(&calls))
        .fold(f64::INFINITY, f64::min);
    let gflop = calls.iter().map(|c| c.flops()).sum::<u64>() as f64 / 1e9;
    let gflops = gflop / seconds.max(1e-12);
    Ok(ProductsAlone {
        calls: calls.len(),
        gflop,
        seconds,
        gflops,
        fraction_of_core_peak: if core_peak > 0.0 {
            gflops / core_peak
        } else {
            0.0
        },
        share_of_step: seconds / threads as f64 / per_step.max(1e-12),
    })
}

/// The peak f32 GFLOP/s of `threads` cores (see the module doc), with how it was found.
fn peak_gflops(threads: usize) -> (f64, String) {
    let ghz = measured_ghz();
    if let Some((core, lanes)) = measured_fma_gflops() {
        let per_cycle = ghz.map_or(String::new(), |g| {
            format!(": {:.0} flops a cycle at {g:.2} GHz", core / g)
        });
        return (
            threads as f64 * core,
            format!(
                "{threads} cores x {core:.1} GFLOP/s, measured with {lanes}-lane FMAs{per_cycle}"
            ),
        );
    }
    // 128-bit vectors (SSE, NEON), two units: an assumption, not a measurement
    let ghz = ghz.unwrap_or(0.0);
    (
        threads as f64 * 2.0 * 4.0 * 2.0 * ghz,
        format!("{threads} cores x 2 FMA x 4 lanes x 2 flops x {ghz:.2} GHz (assumed)"),
    )
}

/// One core's f32 GFLOP/s in fused multiply-adds on its widest vectors and their lanes: twelve
/// independent chains of register FMAs (more than latency × throughput on any x86 core), the
/// fastest of three runs of about a tenth of a second.
#[cfg(target_arch = "x86_64")]
fn measured_fma_gflops() -> Option<(f64, usize)> {
    const ITERATIONS: u64 = 20_000_000; // of 12 FMAs each
    let avx512 = cfg!(feature = "avx512") && std::is_x86_feature_detected!("avx512f");
    let (lanes, chains): (usize, unsafe fn(u64)) = if avx512 {
        (16, fma_chains_avx512)
    } else if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        (8, fma_chains_avx2)
    } else {
        return None;
    };
    let seconds = (0..3)
        .map(|_| {
            let started = Instant::now();
            // SAFETY: the processor has the features `chains` is compiled for (checked above).
            unsafe { chains(ITERATIONS) };
            started.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min);
    let flops = ITERATIONS as f64 * 12.0 * lanes as f64 * 2.0;
    (seconds > 0.0).then(|| (flops / seconds / 1e9, lanes))
}

/// No FMA probe off x86.
#[cfg(not(target_arch = "x86_64"))]
fn measured_fma_gflops() -> Option<(f64, usize)> {
    None
}

/// `n` rounds of twelve independent 16-lane FMAs on registers (zeros: no subnormals).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn fma_chains_avx512(n: u64) {
    // SAFETY: register arithmetic only, on registers declared clobbered; no memory is touched.
    unsafe {
        std::arch::asm!(
            "vpxord zmm0, zmm0, zmm0", "vmovaps zmm1, zmm0", "vmovaps zmm2, zmm0",
            "vmovaps zmm3, zmm0", "vmovaps zmm4, zmm0", "vmovaps zmm5, zmm0",
            "vmovaps zmm6, zmm0", "vmovaps zmm7, zmm0", "vmovaps zmm8, zmm0",
            "vmovaps zmm9, zmm0", "vmovaps zmm10, zmm0", "vmovaps zmm11, zmm0",
            "vmovaps zmm12, zmm0", "vmovaps zmm13, zmm0",
            "2:",
            "vfmadd231ps zmm0, zmm12, zmm13", "vfmadd231ps zmm1, zmm12, zmm13",
            "vfmadd231ps zmm2, zmm12, zmm13", "vfmadd231ps zmm3, zmm12, zmm13",
            "vfmadd231ps zmm4, zmm12, zmm13", "vfmadd231ps zmm5, zmm12, zmm13",
            "vfmadd231ps zmm6, zmm12, zmm13", "vfmadd231ps zmm7, zmm12, zmm13",
            "vfmadd231ps zmm8, zmm12, zmm13", "vfmadd231ps zmm9, zmm12, zmm13",
            "vfmadd231ps zmm10, zmm12, zmm13", "vfmadd231ps zmm11, zmm12, zmm13",
            "dec {n}",
            "jnz 2b",
            n = inout(reg) n => _,
            out("zmm0") _, out("zmm1") _, out("zmm2") _, out("zmm3") _, out("zmm4") _,
            out("zmm5") _, out("zmm6") _, out("zmm7") _, out("zmm8") _, out("zmm9") _,
            out("zmm10") _, out("zmm11") _, out("zmm12") _, out("zmm13") _,
            options(nomem, nostack),
        );
    }
}

/// `n` rounds of twelve independent 8-lane FMAs on registers (zeros: no subnormals).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn fma_chains_avx2(n: u64) {
    // SAFETY: register arithmetic only, on registers declared clobbered; no memory is touched.
    unsafe {
        std::arch::asm!(
            "vxorps ymm0, ymm0, ymm0", "vmovaps ymm1, ymm0", "vmovaps ymm2, ymm0",
            "vmovaps ymm3, ymm0", "vmovaps ymm4, ymm0", "vmovaps ymm5, ymm0",
            "vmovaps ymm6, ymm0", "vmovaps ymm7, ymm0", "vmovaps ymm8, ymm0",
            "vmovaps ymm9, ymm0", "vmovaps ymm10, ymm0", "vmovaps ymm11, ymm0",
            "vmovaps ymm12, ymm0", "vmovaps ymm13, ymm0",
            "2:",
            "vfmadd231ps ymm0, ymm12, ymm13", "vfmadd231ps ymm1, ymm12, ymm13",
            "vfmadd231ps ymm2, ymm12, ymm13", "vfmadd231ps ymm3, ymm12, ymm13",
            "vfmadd231ps ymm4, ymm12, ymm13", "vfmadd231ps ymm5, ymm12, ymm13",
            "vfmadd231ps ymm6, ymm12, ymm13", "vfmadd231ps ymm7, ymm12, ymm13",
            "vfmadd231ps ymm8, ymm12, ymm13", "vfmadd231ps ymm9, ymm12, ymm13",
            "vfmadd231ps ymm10, ymm12, ymm13", "vfmadd231ps ymm11, ymm12, ymm13",
            "dec {n}",
            "jnz 2b",
            n = inout(reg) n => _,
            out("ymm0") _, out("ymm1") _, out("ymm2") _, out("ymm3") _, out("ymm4") _,
            out("ymm5") _, out("ymm6") _, out("ymm7") _, out("ymm8") _, out("ymm9") _,
            out("ymm10") _, out("ymm11") _, out("ymm12") _, out("ymm13") _,
            options(nomem, nostack),
        );
    }
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
        BatchSpec::Transition { batch, frames, .. } => Batch::Transition(TransitionBatch {
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
    let experiment = match &args.config {
        Some(path) => ExperimentConfig::load(path)?,
        None => ExperimentConfig::default(),
    };
    let mut agent: AgentConfig = experiment.agent;
    agent.algo = args.algo;
    let beams = ctxrace_config::LidarConfig::default().beams;
    let spec = agent.batch_spec();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = random_batch(spec, beams, &mut rng);

    let threads = args.threads.unwrap_or(agent.algo.learner_threads());
    let mut algo = ctxrace_learner::build(&agent, beams, threads)?;
    // the diagnostics on the steps a run logs, as in a run
    algo.set_diagnostics_every(experiment.train.log_every);
    algo.train_step(&batch)?;
    let steps = timed_steps(algo.as_mut(), &batch, args.steps)?;
    let (peak, peak_from) = peak_gflops(threads);
    let gflops = steps.gflop_per_step / steps.per_step;
    let alone = products_alone(
        algo.as_mut(),
        &batch,
        (threads, peak / threads as f64, steps.per_step),
    )?;

    let mut policy = Policy::new(&agent, beams, &algo.policy_weights()?, 0)?;
    let times = act_ms(&mut policy, beams, &mut rng, args.act_steps)?;
    let pct = |q: f64| times[((times.len() - 1) as f64 * q).round() as usize];
    let report = LearnerReport {
        algo: agent.algo.to_string(),
        batch: match spec {
            BatchSpec::Sequence { batch, length } => format!("{batch} x {length} sequences"),
            BatchSpec::Transition { batch, frames, .. } => {
                format!("{batch} transitions x {frames} frames")
            }
        },
        threads,
        seconds_per_step: steps.per_step,
        seconds_min: steps.seconds[0],
        seconds_median: steps.seconds[steps.seconds.len() / 2],
        steps_per_second: 1.0 / steps.per_step,
        act_ms_mean: times.iter().sum::<f64>() / times.len() as f64,
        act_ms_p50: pct(0.5),
        act_ms_p90: pct(0.9),
        gflop_per_step: steps.gflop_per_step,
        gflop_by_phase: steps.gflop_by_phase,
        seconds_by_phase: steps.seconds_by_phase,
        gflops,
        peak_gflops: peak,
        peak_from,
        fraction_of_peak: if peak > 0.0 { gflops / peak } else { 0.0 },
        products_alone: alone,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    Ok(())
}

/// The figures of the timed gradient steps.
struct TimedSteps {
    /// Seconds of each step, fastest first.
    seconds: Vec<f64>,
    /// Their mean.
    per_step: f64,
    /// Matrix-product GFLOP of a step: their mean in all, the last step's by phase.
    gflop_per_step: f64,
    gflop_by_phase: Vec<(String, f64)>,
    /// Median seconds of each phase.
    seconds_by_phase: Vec<(String, f64)>,
}

/// Times `steps` gradient steps (at least one) of `algo` on `batch`, counting their matrix
/// products' flops and, from their metrics, each phase's seconds.
fn timed_steps(
    algo: &mut dyn ctxrace_learner::Algorithm,
    batch: &Batch,
    steps: usize,
) -> Result<TimedSteps> {
    let flops_before = ctxrace_nn::kernels::matmul_flops();
    let mut metrics = ctxrace_learner::Metrics::default();
    let mut seconds = Vec::with_capacity(steps.max(1));
    let mut phase_times: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for _ in 0..steps.max(1) {
        let t = Instant::now();
        metrics = algo.train_step(batch)?;
        seconds.push(t.elapsed().as_secs_f64());
        for (k, v) in &metrics {
            if let Some(phase) = k.strip_prefix("seconds/") {
                phase_times.entry(phase.to_string()).or_default().push(*v);
            }
        }
    }
    let per_step = seconds.iter().sum::<f64>() / seconds.len() as f64;
    seconds.sort_by(f64::total_cmp);
    let flops = ctxrace_nn::kernels::matmul_flops() - flops_before;
    let gflop_by_phase = metrics
        .iter()
        .filter_map(|(k, v)| Some((k.strip_prefix("flops/")?.to_string(), v * 1e-9)))
        .collect();
    let seconds_by_phase = phase_times
        .into_iter()
        .map(|(phase, mut times)| {
            times.sort_by(f64::total_cmp);
            (phase, times[times.len() / 2])
        })
        .collect();
    Ok(TimedSteps {
        seconds,
        per_step,
        gflop_per_step: flops as f64 / steps.max(1) as f64 / 1e9,
        gflop_by_phase,
        seconds_by_phase,
    })
}

/// Milliseconds of `steps` acts (at least one) of `policy` at batch 1 on one random
/// observation of `beams` beams, fastest first.
fn act_ms(
    policy: &mut Policy,
    beams: usize,
    rng: &mut ChaCha8Rng,
    steps: usize,
) -> Result<Vec<f64>> {
    let obs: Vec<f32> = (0..beams).map(|_| rng.random_range(0.0..1.0)).collect();
    let mut times = Vec::with_capacity(steps);
    for _ in 0..steps.max(1) {
        let t = Instant::now();
        policy.act(&obs, [0.1, -0.1], false)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    Ok(times)
}

/// Prints `report` as text: the step and acting times, the matrix products' rate against the
/// peak and alone, and each phase's median.
fn print_report(report: &LearnerReport) {
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
    let alone = &report.products_alone;
    println!(
        "  the same products alone ({} gemm calls, {:.2} GFLOP, replayed on one core): \
         {:.1} ms, {:.1} GFLOP/s = {:.1}% of a core's peak; over {} threads they would take \
         {:.1}% of the step",
        alone.calls,
        alone.gflop,
        alone.seconds * 1e3,
        alone.gflops,
        100.0 * alone.fraction_of_core_peak,
        report.threads,
        100.0 * alone.share_of_step
    );
    let phases = phase_medians(report);
    if !phases.is_empty() {
        println!("  median by phase: {}", phases.join(", "));
    }
}

/// Each phase's median time with its matrix products' rate, as `print_report` words them.
fn phase_medians(report: &LearnerReport) -> Vec<String> {
    let gflop_of = |phase: &str| {
        let found = report.gflop_by_phase.iter().find(|(p, _)| p == phase);
        found.map_or(0.0, |(_, g)| *g)
    };
    report
        .seconds_by_phase
        .iter()
        .map(|(phase, s)| {
            let rate = gflop_of(phase) / s.max(1e-12);
            format!("{phase} {:.1} ms ({rate:.1} GFLOP/s)", s * 1e3)
        })
        .collect()
}
