//! `ctxrace eval`: the paper's evaluation protocol. Every context of an `n × n` grid over
//! `[−range, range]²` is raced for `laps` fresh seeded episodes by a trained agent or a
//! reference policy, spread over worker processes. As the paper's code did, a trained agent is
//! evaluated at its best checkpoint (the peak of the smoothed training return) and samples its
//! actions and masks, each episode's noise seeded by the episode; `--checkpoint` and `--act`
//! choose otherwise, and `meta.json` records the choice.
//!
//! Each worker appends its finished episodes to `episodes.part-K.csv` in the output directory,
//! so an interrupted evaluation resumes where it stopped: a rerun skips every (context, lap)
//! already on disk. When all are done the rows are merged into `episodes.csv`, summarised per
//! context (`contexts.csv`, `contexts.json`, see `ctxrace_sim::evaluation`) and one episode is drawn
//! (`episode.png`, `episode.svg`). A cMask agent's masks at every decision go to
//! `masks.part-K.csv` beside, merged into `masks.csv.gz` ([`ctxrace_sim::masks`]).

use crate::ego::EgoSpec;
use ctxrace_render::race::{race_title, render_race, Frame};
use ctxrace_run::lock::{die_with_parent, DirLock};

use crate::TrackArgs;
use anyhow::{bail, Context as _, Result};
use clap::Args;
use clap::ValueEnum;
use ctxrace_config::config_file::read_config_table;
use ctxrace_config::{Context, ContextMode, RaceConfig};
use ctxrace_run::results;
use ctxrace_run::run_dir::{EVAL_DIR, EVAL_JOB};
use ctxrace_run::trained::CheckpointChoice;
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::eval_dir;
use ctxrace_sim::evaluation::{episode_seed, run_episode, EvalMeta, SplitMeans, ToldContext};
use ctxrace_sim::masks::{self, MaskRecorder};
use ctxrace_sim::scenario::{EvalScenario, ScenarioChoice};
use ctxrace_sim::track_check::{check_track, CheckPlan};
use ctxrace_sim::RaceEnv;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Arc;
use std::time::Duration;

/// Arguments of `ctxrace eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// A run directory, a checkpoint directory, an MLP policy file (`*.safetensors`, written by
    /// Python's ctxrace.save_mlp_policy), or a reference policy: `pure-pursuit`,
    /// `follow-the-gap` or `random`.
    source: String,
    /// Which checkpoint of a run directory: `best` (the peak of the smoothed training return,
    /// the paper's), `latest`, `step-N` or `best-at-N` (the best policy after N env steps, kept
    /// by `[train] keep_best_at`).
    #[arg(long, default_value_t = CheckpointChoice::default())]
    checkpoint: CheckpointChoice,
    /// How a trained agent acts: `sample` its distributions (the paper's) or take their `mode`.
    #[arg(long, value_enum, default_value_t = ActMode::default())]
    act: ActMode,
    /// Race scenario TOML (e.g. configs/scenarios/paper-code.toml) in place of a trained
    /// agent's run's race (its rivals stay, unless --rivals) or, for a reference policy, of the
    /// default scenario [default: the run's race; the default scenario].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Grid points per context dimension.
    #[arg(long, default_value_t = eval_dir::GRID)]
    grid: usize,
    /// Half-width of the context grid.
    #[arg(long, default_value_t = eval_dir::RANGE)]
    range: f64,
    /// Race only these contexts of the grid, by index in its `c_v`-major order (the paper's
    /// code's): a list of indices and ranges (`17-48,3`), or `skip-first:K` (the paper branch,
    /// c0fd903, skipped its first 17) [default: all].
    #[arg(long)]
    contexts: Option<String>,
    /// Episodes (laps) per context.
    #[arg(long, default_value_t = eval_dir::LAPS)]
    laps: usize,
    /// Worker processes [default: the number of cores].
    #[arg(long)]
    workers: Option<usize>,
    /// Seed of the evaluation episodes.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory [default: <run>/eval for a run, eval-<policy>-<track>-<rivals>r for a
    /// reference policy or an MLP file (its stem)].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Track [default: the run's; f1_esp for a reference policy].
    #[arg(long)]
    track: Option<String>,
    /// Number of rivals [default: the run's; 3 for a reference policy].
    #[arg(long)]
    rivals: Option<usize>,
    /// Training context range that separates in- from out-of-distribution [default: the
    /// run's; 0.15 for a reference policy].
    #[arg(long)]
    train_range: Option<f64>,
    /// What a cRSSM or cMask agent is told about the rivals' context (the context ablation):
    /// the `true` one (the protocol), `zeros`, or an `other` raced context drawn per episode;
    /// the rivals always drive by the true one.
    #[arg(long, value_enum, default_value_t = ToldContext::True)]
    told_context: ToldContext,
    /// Fix a cMask agent's mask at `M_V,M_THETA` (each in [0, 1], e.g. `1,0`) instead of
    /// letting its mask network choose (the context ablation).
    #[arg(long, value_parser = parse_mask)]
    mask: Option<Mask>,
    /// Discard earlier results in the output directory instead of resuming.
    #[arg(long)]
    fresh: bool,
    #[command(flatten)]
    tracks: TrackArgs,
}

/// Everything a worker needs, written by the coordinator as `job.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct EvalJob {
    meta: EvalMeta,
    /// What the workers load: the resolved checkpoint directory as this machine reaches it, or
    /// the baseline's name (`meta.source` is the portable name the records keep).
    ego: String,
    race: RaceConfig,
    tracks: TrackArgs,
    /// `(context index, lap)` pairs left to run, in order.
    todo: Vec<(usize, usize)>,
}

/// Arguments of the hidden `ctxrace eval-worker` role.
#[derive(Args)]
pub struct WorkerArgs {
    /// The coordinator's job file.
    #[arg(long)]
    job: PathBuf,
    /// This worker's index.
    #[arg(long)]
    shard: usize,
    /// Number of workers.
    #[arg(long)]
    shards: usize,
}

/// A fixed cMask mask `[m_v, m_θ]`.
#[derive(Clone, Copy, Debug)]
struct Mask([f32; 2]);

/// Parses `--mask M_V,M_THETA`.
fn parse_mask(text: &str) -> std::result::Result<Mask, String> {
    let values: Vec<&str> = text.split(',').collect();
    let parsed: Vec<f32> = values
        .iter()
        .filter_map(|v| v.trim().parse::<f32>().ok())
        .filter(|v| (0.0..=1.0).contains(v))
        .collect();
    match parsed[..] {
        [v, t] if values.len() == 2 => Ok(Mask([v, t])),
        _ => Err(format!(
            "'{text}' is not two mask values in [0, 1] separated by a comma, e.g. 1,0"
        )),
    }
}

/// The trained agent (checkpoint `choice` of a run) or reference policy named by `source`.
fn ego_spec(source: &str, choice: CheckpointChoice) -> Result<EgoSpec> {
    match source.parse::<BaselineKind>() {
        Ok(kind) => Ok(EgoSpec::Baseline(kind)),
        Err(_) => EgoSpec::load(Path::new(source), choice),
    }
}

/// Refuses a context ablation the ego cannot take: a told context for an agent that reads
/// none, a fixed mask for an agent without one.
fn check_ablation(spec: &EgoSpec, told: ToldContext, mask: Option<Mask>) -> Result<()> {
    let mode = match spec {
        EgoSpec::Trained(t) => t.agent.algo.context_mode(),
        EgoSpec::Baseline(_) | EgoSpec::Mlp(..) => ContextMode::None,
    };
    if !told.is_true() && mode == ContextMode::None {
        bail!(
            "--told-context {}: {} reads no context; the context ablation is for cRSSM and cMask \
             agents",
            told.to_possible_value()
                .map_or("?".into(), |v| v.get_name().to_string()),
            spec.name()
        );
    }
    if mask.is_some() && mode != ContextMode::Cmask {
        bail!(
            "--mask: {} has no context mask; only a cMask agent's mask can be fixed",
            spec.name()
        );
    }
    Ok(())
}

/// Runs the protocol.
pub fn run(args: EvalArgs) -> Result<()> {
    check_grid(&args)?;
    let spec = ego_spec(&args.source, args.checkpoint)?;
    check_ablation(&spec, args.told_context, args.mask)?;
    let EvalScenario {
        track,
        race,
        train_range,
    } = scenario(&args, &spec)?;
    warn_of_track(&args, &track, &race)?;
    let out = out_dir(&args, &spec, &track, &race);
    let meta = eval_meta(&args, &spec, track, &race, train_range)?;
    let lock = DirLock::acquire(&out)?;
    eval_dir::prepare(&out, &meta, args.fresh)?;

    let todo = eval_dir::todo(&out, &meta)?;
    let total = (meta.raced().len() * meta.laps) as u64;
    let done = total - todo.len() as u64;
    let job = EvalJob {
        meta: meta.clone(),
        ego: spec.source(),
        race: race.clone(),
        tracks: args.tracks.clone(),
        todo,
    };
    if !job.todo.is_empty() {
        let workers = args
            .workers
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
            .clamp(1, job.todo.len());
        let job_path = out.join(EVAL_JOB);
        results::write_json(&job_path, &job)?;
        let progress = (done, total);
        run_workers(&out, &meta, &job_path, workers, progress, &lock)?;
    }
    finish(&out, &meta, &race, &args.tracks, &spec)
}

/// Refuses an empty grid or lap count and a grid range beyond the contexts' ±0.9.
fn check_grid(args: &EvalArgs) -> Result<()> {
    if args.grid == 0 || args.laps == 0 {
        bail!("--grid and --laps must be positive");
    }
    if !(args.range.is_finite() && (0.0..=0.9).contains(&args.range)) {
        bail!(
            "--range {} must lie in [0, 0.9] (contexts are limited to ±0.9)",
            args.range
        );
    }
    Ok(())
}

/// The track, race and training range the evaluation races: the trained agent's run's, or
/// the default scenario's, as `--config`, `--track`, `--rivals` and `--train-range` change them.
fn scenario(args: &EvalArgs, spec: &EgoSpec) -> Result<EvalScenario> {
    let experiment = match spec {
        EgoSpec::Trained(t) => t.experiment.as_ref(),
        EgoSpec::Baseline(_) | EgoSpec::Mlp(..) => None,
    };
    let mut race_keys = toml::Table::new();
    if args.tracks.raceline_file {
        race_keys.insert("shipped_raceline".into(), true.into());
    }
    let choice = ScenarioChoice {
        track: args.track.clone(),
        rivals: args.rivals,
        train_range: args.train_range,
        race: args.config.as_deref().map(read_config_table).transpose()?,
        race_keys,
    };
    EvalScenario::resolve(experiment, choice).with_context(|| match &args.config {
        Some(path) => format!("the race of --config {}", path.display()),
        None => "the run's race".into(),
    })
}

/// Checks the track over the grid and warns of each failure: the protocol's rows mean little
/// where the rivals or the reference ego crash on their own.
fn warn_of_track(args: &EvalArgs, track: &str, race: &RaceConfig) -> Result<()> {
    let check = CheckPlan {
        grid: args.grid,
        range: args.range,
        places: race.rivals,
    };
    let report = check_track(Arc::new(args.tracks.load(track, race)?), race, check)?;
    for f in report.failures() {
        eprintln!("warning: {track}: {}: {}", f.check, f.detail);
    }
    Ok(())
}

/// The output directory: `--out`, else the run's `eval` (a checkpoint given alone: its own),
/// else a reference policy's folder named by its policy, track and rivals.
fn out_dir(args: &EvalArgs, spec: &EgoSpec, track: &str, race: &RaceConfig) -> PathBuf {
    match (&args.out, spec) {
        (Some(o), _) => o.clone(),
        (None, EgoSpec::Trained(t)) => match t.checkpoint.parent().and_then(Path::parent) {
            Some(run) if t.experiment.is_some() => run.join(EVAL_DIR),
            _ => t.checkpoint.join(EVAL_DIR),
        },
        (None, EgoSpec::Baseline(_) | EgoSpec::Mlp(..)) => {
            eval_dir::reference_dir(&spec.name(), track, race.rivals)
        }
    }
}

/// The evaluation's `meta.json`: what is raced, by which ego and how.
fn eval_meta(
    args: &EvalArgs,
    spec: &EgoSpec,
    track: String,
    race: &RaceConfig,
    train_range: f64,
) -> Result<EvalMeta> {
    Ok(EvalMeta {
        algo: spec.name(),
        track,
        rivals: race.rivals,
        train_seed: match spec {
            EgoSpec::Trained(t) => t.agent.seed(),
            EgoSpec::Baseline(_) | EgoSpec::Mlp(..) => 0,
        },
        train_range,
        grid: args.grid,
        range: args.range,
        laps: args.laps,
        seed: args.seed,
        source: match spec {
            EgoSpec::Trained(t) => portable_source(&t.checkpoint, t.experiment.is_some()),
            EgoSpec::Baseline(_) | EgoSpec::Mlp(..) => spec.name(),
        },
        checkpoint: match spec {
            EgoSpec::Trained(t) if t.experiment.is_some() => args.checkpoint.to_string(),
            EgoSpec::Trained(_) | EgoSpec::Mlp(..) => "given".into(),
            EgoSpec::Baseline(_) => "-".into(),
        },
        act: args.act,
        preset: race.preset,
        contexts: args
            .contexts
            .as_deref()
            .map(|spec| eval_dir::parse_contexts(spec, args.grid * args.grid))
            .transpose()?,
        told: args.told_context,
        mask: args.mask.map(|m| m.0),
    })
}

/// Starts the workers and waits for them, showing progress (episodes `(done, total)`) from
/// their result files. The workers die with this process and hold `out`'s `lock` with it, so
/// that a rerun cannot start before the last of them has exited.
fn run_workers(
    out: &Path,
    meta: &EvalMeta,
    job: &Path,
    workers: usize,
    (done, total): (u64, u64),
    lock: &DirLock,
) -> Result<()> {
    let exe = std::env::current_exe().context("locating the ctxrace binary")?;
    let mut children: Vec<Child> = (0..workers)
        .map(|k| {
            let mut worker = Command::new(&exe);
            worker.arg("eval-worker").arg("--job").arg(job).args([
                "--shard",
                &k.to_string(),
                "--shards",
                &workers.to_string(),
            ]);
            die_with_parent(&mut worker);
            lock.share_with(&mut worker);
            worker.spawn().context("starting an evaluation worker")
        })
        .collect::<Result<_>>()?;
    let bar = crate::progress::progress_bar(total, "episodes");
    bar.set_position(done);
    let mut failed = Vec::new();
    while !children.is_empty() {
        std::thread::sleep(Duration::from_millis(500));
        let mut running = Vec::new();
        for mut child in children {
            match child.try_wait()? {
                Some(status) if !status.success() => failed.push(status),
                Some(_) => {}
                None => running.push(child),
            }
        }
        children = running;
        bar.set_position(eval_dir::read_parts(out, meta)?.len() as u64);
    }
    bar.finish();
    if !failed.is_empty() {
        bail!(
            "{} evaluation worker(s) failed ({failed:?}); rerun the same command to resume",
            failed.len()
        );
    }
    Ok(())
}

/// The `eval-worker` role: runs every `shards`-th pending episode of the job, appending rows.
pub fn run_worker(args: WorkerArgs) -> Result<()> {
    let job: EvalJob = results::read_json(&args.job)?;
    let out = args.job.parent().unwrap_or(Path::new("."));
    let spec = ego_spec(&job.ego, CheckpointChoice::Latest)?;
    let track = Arc::new(job.tracks.load(&job.meta.track, &job.race)?);
    let mut env = RaceEnv::new(track, job.race.clone())?;
    let mut driver = spec.driver(&env, job.meta.act)?;
    driver.fix_mask(job.meta.mask)?;
    let grid = job.meta.grid_contexts();
    let raced = job.meta.raced();
    let mut writer = eval_dir::append_csv(&eval_dir::part_path(out, args.shard))?;
    let mut masks = None;
    for &(index, lap) in job.todo.iter().skip(args.shard).step_by(args.shards) {
        let context = grid[index];
        let seed = episode_seed(job.meta.seed, index, lap);
        driver.tell(job.meta.told.told(&grid, &raced, index, seed));
        let mut recorder = MaskRecorder::new(context, lap);
        let episode = run_episode(&mut env, &mut driver, context, seed, lap, |env, d| {
            recorder.observe(env, &d)
        })?;
        // an episode's masks before its row: a resumed evaluation never lacks them
        let rows = recorder.into_rows();
        if !rows.is_empty() {
            let masks = match masks.as_mut() {
                Some(open) => open,
                None => masks.insert(eval_dir::append_csv(&masks::part_path(out, args.shard))?),
            };
            for row in rows {
                masks.serialize(row)?;
            }
            masks.flush()?;
        }
        writer.serialize(episode)?;
        writer.flush()?;
    }
    Ok(())
}

/// Merges the workers' rows, writes the per-context summaries, draws one episode and prints
/// the in- and out-of-distribution means.
fn finish(
    out: &Path,
    meta: &EvalMeta,
    race: &RaceConfig,
    tracks: &TrackArgs,
    spec: &EgoSpec,
) -> Result<()> {
    let eval_dir::Merged { summary, mask_rows } = eval_dir::merge(out, meta)?;

    let track = Arc::new(tracks.load(&meta.track, race)?);
    let mut env = RaceEnv::new(track.clone(), race.clone())?;
    let mut driver = spec.driver(&env, meta.act)?;
    driver.fix_mask(meta.mask)?;
    let mut frames = Vec::new();
    let centre = Context::default();
    run_episode(
        &mut env,
        &mut driver,
        centre,
        episode_seed(meta.seed, usize::MAX, 0),
        0,
        |env, d| frames.push(Frame::capture(env, d.action, d.reward, d.obs)),
    )?;
    for ext in ["png", "svg"] {
        let title = race_title(&meta.track, &spec.name(), &env);
        render_race(&out.join(format!("episode.{ext}")), &track, &frames, &title)?;
    }

    let mut stdout = std::io::stdout().lock();
    writeln!(
        stdout,
        "{} on {} with {} rival(s): {} contexts x {} laps -> {}",
        meta.algo,
        meta.track,
        meta.rivals,
        summary.len(),
        meta.laps,
        out.display()
    )?;
    for (label, inside) in [("in-distribution", true), ("out-of-distribution", false)] {
        let Some(m) = SplitMeans::split(&summary, inside) else {
            continue;
        };
        writeln!(
            stdout,
            "  {label:>20} ({:2} contexts): PG {:.3}  OT {:+.3}  A2A {:.2}/50  wall {:.1}%",
            m.contexts,
            m.progress,
            m.overtakes,
            m.a2a,
            100.0 * m.wall_crash
        )?;
    }
    if let Some(rows) = mask_rows {
        writeln!(
            stdout,
            "  cMask's masks: {rows} decisions -> {}",
            out.join(masks::MASKS_FILE).display()
        )?;
    }
    Ok(())
}

/// The checkpoint as `meta.json` records it, free of the machine that ran it: a run's
/// checkpoint as `<run>/checkpoints/<name>`, a checkpoint folder given alone by its name.
fn portable_source(checkpoint: &Path, in_run: bool) -> String {
    let keep = if in_run { 3 } else { 1 };
    let parts: Vec<_> = checkpoint
        .components()
        .filter_map(|c| match c {
            std::path::Component::Normal(p) => Some(p.to_string_lossy()),
            _ => None,
        })
        .collect();
    parts[parts.len().saturating_sub(keep)..].join("/")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_recorded_source_names_no_machine_folder() {
        let run = Path::new("/home/me/runs/cmask-f1_esp-1r-s7/checkpoints/best");
        assert_eq!(
            portable_source(run, true),
            "cmask-f1_esp-1r-s7/checkpoints/best"
        );
        assert_eq!(portable_source(Path::new("/tmp/x/ckpt/"), false), "ckpt");
        assert_eq!(portable_source(Path::new("best"), true), "best");
    }

    #[test]
    fn a_mask_is_two_values_in_the_unit_interval() {
        assert_eq!(parse_mask("1,0").unwrap().0, [1.0, 0.0]);
        assert_eq!(parse_mask(" 0.5 , 1").unwrap().0, [0.5, 1.0]);
        for bad in ["1", "1,0,1", "1.5,0", "a,b", "-0.1,0", "NaN,0", ""] {
            let err = parse_mask(bad).unwrap_err();
            assert!(err.contains("e.g. 1,0"), "{bad}: {err}");
        }
    }
}
