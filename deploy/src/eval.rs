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
//! `masks.part-K.csv` beside, merged into `masks.csv.gz` ([`crate::masks`]).

use crate::ego::EgoSpec;
use crate::lock::{die_with_parent, DirLock};
use crate::masks::{self, MaskRecorder};
use crate::render::{race_title, render_race, Frame};

use crate::track_check::{check_track, CheckPlan};
use crate::TrackArgs;
use anyhow::{bail, Context as _, Result};
use clap::Args;
use ctxrace_config::{Context, RaceConfig};
use ctxrace_learner::trained::{CheckpointChoice, TrainedAgent};
use ctxrace_run::results;
use ctxrace_run::run_dir::{
    open_append, read_regular, write_atomic, EVAL_CONTEXTS_CSV, EVAL_CONTEXTS_JSON, EVAL_DIR,
    EVAL_EPISODES, EVAL_JOB, EVAL_META,
};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::evaluation::{
    self, episode_seed, run_episode, ContextSummary, EvalEpisode, EvalMeta,
};
use ctxrace_sim::RaceEnv;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Arc;
use std::time::Duration;

/// Arguments of `ctxrace eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// A run directory, a checkpoint directory, or a reference policy: `pure-pursuit`,
    /// `follow-the-gap` or `random`.
    source: String,
    /// Which checkpoint of a run directory: `best` (the peak of the smoothed training return,
    /// the paper's), `latest` or `step-N`.
    #[arg(long, default_value = "best")]
    checkpoint: CheckpointChoice,
    /// How a trained agent acts: `sample` its distributions (the paper's) or take their `mode`.
    #[arg(long, value_enum, default_value_t = ActMode::Sample)]
    act: ActMode,
    /// Race scenario TOML for a reference policy (e.g. configs/scenarios/paper-code.toml)
    /// [default: the run's for a trained agent, ctxrace's default scenario otherwise].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Grid points per context dimension.
    #[arg(long, default_value_t = 7)]
    grid: usize,
    /// Half-width of the context grid.
    #[arg(long, default_value_t = 0.3)]
    range: f64,
    /// Race only these contexts of the grid, by index in its `c_v`-major order (the paper's
    /// code's): a list of indices and ranges (`17-48,3`), or `skip-first:K` (the paper branch,
    /// c0fd903, skipped its first 17) [default: all].
    #[arg(long)]
    contexts: Option<String>,
    /// Episodes (laps) per context.
    #[arg(long, default_value_t = 50)]
    laps: usize,
    /// Worker processes [default: the number of cores].
    #[arg(long)]
    workers: Option<usize>,
    /// Seed of the evaluation episodes.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory [default: <run>/eval for a run, eval-<policy>-<track>-<rivals>r for a
    /// reference policy].
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

/// The contexts of an evaluation's grid (all of them, raced or not: indices stay the grid's).
fn contexts(meta: &EvalMeta) -> Vec<Context> {
    Context::grid(meta.grid, meta.range)
}

/// The grid indices an evaluation races.
fn raced(meta: &EvalMeta) -> Vec<usize> {
    match &meta.contexts {
        Some(chosen) => chosen.clone(),
        None => (0..meta.grid * meta.grid).collect(),
    }
}

/// Parses `--contexts` for a grid of `n` contexts: `skip-first:K`, or a comma-separated list
/// of indices and inclusive ranges `a-b`. Returns the sorted, distinct indices.
pub fn parse_contexts(spec: &str, n: usize) -> Result<Vec<usize>> {
    let bad = |why: String| {
        anyhow::anyhow!(
            "--contexts {spec:?}: {why}; give indices 0 to {} of the grid (c_v major), \
             ranges such as 17-48, or skip-first:K",
            n - 1
        )
    };
    let index = |t: &str| -> Result<usize> {
        let i: usize = t
            .trim()
            .parse()
            .map_err(|_| bad(format!("{t:?} is not an index")))?;
        if i >= n {
            return Err(bad(format!("{i} is outside the grid")));
        }
        Ok(i)
    };
    let mut chosen = Vec::new();
    if let Some(k) = spec.strip_prefix("skip-first:") {
        let k: usize = k
            .trim()
            .parse()
            .map_err(|_| bad(format!("{k:?} is not a count")))?;
        chosen.extend(k..n);
    } else {
        for part in spec.split(',') {
            match part.split_once('-') {
                Some((a, b)) => chosen.extend(index(a)?..=index(b)?),
                None => chosen.push(index(part)?),
            }
        }
    }
    chosen.sort_unstable();
    chosen.dedup();
    if chosen.is_empty() {
        return Err(bad("it selects no context".into()));
    }
    Ok(chosen)
}

/// The trained agent (checkpoint `choice` of a run) or reference policy named by `source`.
fn ego_spec(source: &str, choice: CheckpointChoice) -> Result<EgoSpec> {
    match source.parse::<BaselineKind>() {
        Ok(kind) => Ok(EgoSpec::Baseline(kind)),
        Err(_) => Ok(EgoSpec::Trained(Box::new(TrainedAgent::load(
            Path::new(source),
            choice,
        )?))),
    }
}

/// Runs the protocol.
pub fn run(args: EvalArgs) -> Result<()> {
    if args.grid == 0 || args.laps == 0 {
        bail!("--grid and --laps must be positive");
    }
    if !(args.range.is_finite() && (0.0..=0.9).contains(&args.range)) {
        bail!(
            "--range {} must lie in [0, 0.9] (contexts are limited to ±0.9)",
            args.range
        );
    }
    let spec = ego_spec(&args.source, args.checkpoint)?;
    let (experiment, train_seed) = match &spec {
        EgoSpec::Trained(t) => (t.experiment.clone(), t.agent.seed()),
        EgoSpec::Baseline(_) => (None, 0),
    };
    if let (Some(_), Some(path)) = (&experiment, &args.config) {
        bail!(
            "--config {} applies to reference policies; a trained agent races in its run's \
             scenario (its config.toml)",
            path.display()
        );
    }
    let mut race = match &experiment {
        Some(e) => e.race.clone(),
        None => crate::load_race_config(args.config.as_ref())?,
    };
    race.shipped_raceline |= args.tracks.raceline_file;
    race.rivals = args
        .rivals
        .unwrap_or(if experiment.is_some() { race.rivals } else { 3 });
    race.validate()?;
    let track = args
        .track
        .clone()
        .or_else(|| experiment.as_ref().map(|e| e.track.clone()))
        .unwrap_or_else(|| "f1_esp".into());
    // the protocol's rows mean little where the rivals or the reference ego crash on their own
    let check = CheckPlan {
        grid: args.grid,
        range: args.range,
        places: race.rivals,
    };
    let report = check_track(Arc::new(args.tracks.load(&track, &race)?), &race, check)?;
    for f in report.failures() {
        eprintln!("warning: {track}: {}: {}", f.check, f.detail);
    }
    let train_range = args
        .train_range
        .or_else(|| experiment.as_ref().map(|e| e.train.context_range))
        .unwrap_or(0.15);
    let out = match (&args.out, &spec) {
        (Some(o), _) => o.clone(),
        (None, EgoSpec::Trained(t)) => match t.checkpoint.parent().and_then(Path::parent) {
            Some(run) if t.experiment.is_some() => run.join(EVAL_DIR),
            _ => t.checkpoint.join(EVAL_DIR),
        },
        (None, EgoSpec::Baseline(_)) => PathBuf::from(format!(
            "eval-{}-{}-{}r",
            spec.name(),
            track.replace([':', '/'], "_"),
            race.rivals
        )),
    };
    let meta = EvalMeta {
        algo: spec.name(),
        track,
        rivals: race.rivals,
        train_seed,
        train_range,
        grid: args.grid,
        range: args.range,
        laps: args.laps,
        seed: args.seed,
        source: match &spec {
            EgoSpec::Trained(t) => t.checkpoint.display().to_string(),
            EgoSpec::Baseline(_) => spec.name(),
        },
        checkpoint: match &spec {
            EgoSpec::Trained(t) if t.experiment.is_some() => args.checkpoint.to_string(),
            EgoSpec::Trained(_) => "given".into(),
            EgoSpec::Baseline(_) => "-".into(),
        },
        act: args.act,
        preset: race.preset,
        contexts: args
            .contexts
            .as_deref()
            .map(|spec| parse_contexts(spec, args.grid * args.grid))
            .transpose()?,
    };
    let lock = DirLock::acquire(&out)?;
    prepare_out_dir(&out, &meta, args.fresh)?;

    let done = finished_episodes(&out, &meta)?;
    let chosen = raced(&meta);
    let todo: Vec<(usize, usize)> = chosen
        .iter()
        .flat_map(|&c| (0..meta.laps).map(move |l| (c, l)))
        .filter(|key| !done.contains(key))
        .collect();
    let total = (chosen.len() * meta.laps) as u64;
    let job = EvalJob {
        meta: meta.clone(),
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
        let progress = (done.len() as u64, total);
        run_workers(&out, &meta, &job_path, workers, progress, &lock)?;
    }
    finish(&out, &meta, &race, &args.tracks, &spec)
}

/// Creates `out`, checks that earlier results belong to the same evaluation (or removes them
/// with `fresh`) and writes `meta.json`.
fn prepare_out_dir(out: &Path, meta: &EvalMeta, fresh: bool) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let meta_path = out.join(EVAL_META);
    if fresh {
        for entry in std::fs::read_dir(out)? {
            let path = entry?.path();
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if ["episodes", "contexts", "masks"]
                .iter()
                .any(|prefix| name.starts_with(prefix))
            {
                std::fs::remove_file(&path)
                    .with_context(|| format!("removing {}", path.display()))?;
            }
        }
    } else if meta_path.exists() {
        let old: EvalMeta = results::read_json(&meta_path)?;
        if &old != meta {
            bail!(
                "{} holds results of another evaluation ({} on {}, {} rivals, grid {}, range {}, \
                 {} laps, seed {}); pass --fresh to replace them or --out for another directory",
                out.display(),
                old.algo,
                old.track,
                old.rivals,
                old.grid,
                old.range,
                old.laps,
                old.seed
            );
        }
    }
    Ok(results::write_json(&meta_path, meta)?)
}

/// Every finished episode on disk with its context's index in the grid of `meta` (a torn
/// last line of a killed worker is skipped).
fn read_parts(out: &Path, meta: &EvalMeta) -> Result<Vec<(usize, EvalEpisode)>> {
    let grid = contexts(meta);
    let chosen = raced(meta);
    let mut rows = Vec::new();
    for part in results::part_files(out, "episodes.part-")? {
        let mut reader =
            csv::Reader::from_path(&part).with_context(|| format!("opening {}", part.display()))?;
        for row in reader.deserialize::<EvalEpisode>() {
            let e = match row {
                Ok(e) => e,
                Err(err) => {
                    tracing::warn!("skipping a torn row of {}: {err}", part.display());
                    continue;
                }
            };
            let index = grid
                .iter()
                .position(|c| c.speed == e.context_speed && c.steer == e.context_steer);
            match index {
                Some(i) if e.lap < meta.laps && chosen.contains(&i) => rows.push((i, e)),
                _ => bail!(
                    "{} holds an episode outside this evaluation (context {}, {}, lap {}); \
                     pass --fresh",
                    part.display(),
                    e.context_speed,
                    e.context_steer,
                    e.lap
                ),
            }
        }
    }
    Ok(rows)
}

/// The `(context index, lap)` pairs already on disk.
fn finished_episodes(out: &Path, meta: &EvalMeta) -> Result<HashSet<(usize, usize)>> {
    Ok(read_parts(out, meta)?
        .into_iter()
        .map(|(c, e)| (c, e.lap))
        .collect())
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
        bar.set_position(read_parts(out, meta)?.len() as u64);
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

/// Cuts a torn last line (a worker killed mid-write) so that appending starts on a fresh line.
fn trim_torn_line(path: &Path) -> Result<()> {
    let bytes = match read_regular(path, u64::MAX) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    if bytes.last().is_some_and(|&b| b != b'\n') {
        let keep = bytes.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
        write_atomic(path, &bytes[..keep])
            .with_context(|| format!("repairing {}", path.display()))?;
    }
    Ok(())
}

/// The `eval-worker` role: runs every `shards`-th pending episode of the job, appending rows.
pub fn run_worker(args: WorkerArgs) -> Result<()> {
    let job: EvalJob = results::read_json(&args.job)?;
    let out = args.job.parent().unwrap_or(Path::new("."));
    // `source` names the resolved checkpoint directory (or the baseline)
    let spec = ego_spec(&job.meta.source, CheckpointChoice::Latest)?;
    let track = Arc::new(job.tracks.load(&job.meta.track, &job.race)?);
    let mut env = RaceEnv::new(track, job.race.clone())?;
    let mut driver = spec.driver(&env, job.meta.act)?;
    let grid = contexts(&job.meta);
    let mut writer = append_csv(&out.join(format!("episodes.part-{:03}.csv", args.shard)))?;
    let mut masks = None;
    for &(index, lap) in job.todo.iter().skip(args.shard).step_by(args.shards) {
        let context = grid[index];
        let seed = episode_seed(job.meta.seed, index, lap);
        let mut recorder = MaskRecorder::new(context, lap);
        let episode = run_episode(&mut env, &mut driver, context, seed, lap, |env, d| {
            recorder.observe(env, &d)
        })?;
        // an episode's masks before its row: a resumed evaluation never lacks them
        let rows = recorder.into_rows();
        if !rows.is_empty() {
            let masks = match masks.as_mut() {
                Some(open) => open,
                None => masks.insert(append_csv(&masks::part_path(out, args.shard))?),
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

/// A CSV writer appending to `path` (after cutting a torn last line), with a header when the
/// file is new or empty.
fn append_csv(path: &Path) -> Result<csv::Writer<std::fs::File>> {
    trim_torn_line(path)?;
    let fresh = !path.exists() || std::fs::metadata(path)?.len() == 0;
    let file = open_append(path).with_context(|| format!("opening {}", path.display()))?;
    Ok(csv::WriterBuilder::new()
        .has_headers(fresh)
        .from_writer(file))
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
    let mut rows = read_parts(out, meta)?;
    rows.sort_by_key(|(c, e)| (*c, e.lap));
    rows.dedup_by_key(|(c, e)| (*c, e.lap));
    let expected = raced(meta).len() * meta.laps;
    if rows.len() != expected {
        bail!(
            "{} holds {} of {expected} episodes; rerun the same command to finish",
            out.display(),
            rows.len()
        );
    }
    let episodes: Vec<EvalEpisode> = rows.into_iter().map(|(_, e)| e).collect();
    results::write_csv(&out.join(EVAL_EPISODES), &episodes)?;
    let summary = evaluation::summarise(&episodes, meta.train_range);
    results::write_csv(&out.join(EVAL_CONTEXTS_CSV), &summary)?;
    results::write_json(&out.join(EVAL_CONTEXTS_JSON), &summary)?;
    let grid = contexts(meta);
    let chosen = raced(meta);
    let kept = |c: Context, lap: usize| {
        lap < meta.laps
            && grid
                .iter()
                .position(|&g| g == c)
                .is_some_and(|i| chosen.contains(&i))
    };
    let masks = masks::merge_parts(out, kept)?;

    let track = Arc::new(tracks.load(&meta.track, race)?);
    let mut env = RaceEnv::new(track.clone(), race.clone())?;
    let mut driver = spec.driver(&env, meta.act)?;
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
        let part: Vec<_> = summary
            .iter()
            .filter(|s| s.in_distribution == inside)
            .collect();
        if part.is_empty() {
            continue;
        }
        let n = part.len() as f64;
        let mean = |f: fn(&ContextSummary) -> f64| part.iter().map(|s| f(s)).sum::<f64>() / n;
        writeln!(
            stdout,
            "  {label:>20} ({:2} contexts): PG {:.3}  OT {:+.3}  A2A {:.2}/50  wall {:.1}%",
            part.len(),
            mean(|s| s.progress),
            mean(|s| s.overtakes),
            mean(|s| s.a2a),
            100.0 * mean(|s| s.wall_crash)
        )?;
    }
    if let Some(rows) = masks {
        writeln!(
            stdout,
            "  cMask's masks: {rows} decisions -> {}",
            out.join(masks::MASKS_FILE).display()
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episode_seeds_are_distinct_across_the_grid() {
        let seeds: HashSet<u64> = (0..49)
            .flat_map(|c| (0..50).map(move |l| episode_seed(7, c, l)))
            .collect();
        assert_eq!(seeds.len(), 49 * 50);
    }

    #[test]
    fn a_context_subset_parses_as_grid_indices() {
        // the paper branch's evaluation: the last 32 of the 49
        assert_eq!(
            parse_contexts("skip-first:17", 49).unwrap(),
            (17..49).collect::<Vec<_>>()
        );
        assert_eq!(parse_contexts("5,0-2, 2", 9).unwrap(), [0, 1, 2, 5]);
        for (spec, why) in [
            ("49", "outside the grid"),
            ("3-x", "not an index"),
            ("skip-first:49", "no context"),
            ("skip-first:-1", "not a count"),
            ("", "not an index"),
        ] {
            let err = parse_contexts(spec, 49).unwrap_err().to_string();
            assert!(
                err.contains("--contexts") && err.contains(why),
                "{spec}: {err}"
            );
        }
    }

    #[test]
    fn a_torn_last_line_is_cut() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("part.csv");
        std::fs::write(&p, "a,b\n1,2\n3,").unwrap();
        trim_torn_line(&p).unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "a,b\n1,2\n");
    }
}
