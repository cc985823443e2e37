//! `ctxrace sweep`: an experiment matrix in one command — the paper's 4 algorithms × 2 tracks ×
//! 1 or 3 rivals × 5 seeds, or any other — each run trained, then evaluated with the paper's
//! protocol, and one report over all of them.
//!
//! A matrix file (`configs/paper/matrix.toml`) names a base experiment config, the values of
//! each axis (`algos`, `tracks`, `rivals`, `seeds`), a table laid over the base for every run
//! (`[experiment]`) and per-algorithm tables laid over that (`[algo.sac]`: the paper code's
//! update ratios). Run `<algo>-<track>-<rivals>r-s<seed>` lives in
//! `<out>/<name>/`, its resolved experiment in `<out>/configs/<name>.toml`; it is done when its
//! evaluation is complete.
//!
//! The sweep skips what is done and resumes what was interrupted: training with `train
//! --resume` (the learner from its newest checkpoint, the replay from its snapshot; an inline
//! run from its resume point, exactly), evaluation from its partial files. It runs at most `--jobs` runs at once,
//! each a child `ctxrace sweep MATRIX --run NAME` in its own process group (its output in
//! `<out>/logs/<name>.log`), the cores shared out between them, and writes the report to
//! `<out>/report/` once every run is in. Ctrl-C stops the runs cleanly (checkpoint, snapshot);
//! rerunning the command continues. `--emit list` prints each run's command and `--emit slurm`
//! a script that submits them as a Slurm array job and the report after it (see
//! [`crate::slurm`]), so that a cluster runs exactly what the local sweep would; `--report`
//! writes the report alone.

use crate::shell::{is_plain, shell_quote};
use anyhow::{bail, Context as _, Result};
use clap::{Args, ValueEnum};
use ctxrace_config::config_file::read_config_text;
use ctxrace_config::validate::toml_message;
use ctxrace_config::{AlgoKind, ContextMode, ExperimentConfig};
use ctxrace_run::lock::{die_with_parent, DirLock};
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::evaluation::ToldContext;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Arguments of `ctxrace sweep`.
#[derive(Args)]
pub struct SweepArgs {
    /// The matrix file (e.g. configs/paper/matrix.toml).
    matrix: PathBuf,
    /// Only the first K of the matrix's seeds.
    #[arg(long)]
    seeds: Option<usize>,
    /// Runs at once; the cores are shared out between them.
    #[arg(long, default_value_t = 1)]
    jobs: usize,
    /// Only the runs with these axis values, e.g. algo=cmask,track=f1_esp (axes: algo, track,
    /// rivals, seed; a key given twice takes either value).
    #[arg(long)]
    only: Option<String>,
    /// Output directory [default: runs/<matrix file stem>].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the commands instead of running them: `list` (one per run) or `slurm` (an array
    /// job script).
    #[arg(long, value_enum)]
    emit: Option<Emit>,
    /// Run only the named run (what each emitted command does).
    #[arg(long)]
    run: Option<String>,
    /// Cores one run may use [default: the machine's divided by --jobs].
    #[arg(long)]
    cores: Option<usize>,
    /// Folder searched for track names, passed to every run [default: $CTXRACE_TRACKS_DIR,
    /// else ../shared/tracks if it exists, else .; pinned as an absolute path when emitted].
    #[arg(long, env = "CTXRACE_TRACKS_DIR")]
    tracks_dir: Option<PathBuf>,
    /// Only write the report over the runs (every one must be evaluated; what a Slurm sweep's
    /// report job runs).
    #[arg(long)]
    report: bool,
    #[command(flatten)]
    slurm: crate::slurm::SlurmArgs,
}

/// What `--emit` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Emit {
    /// One `ctxrace sweep MATRIX --run NAME` command line per run.
    List,
    /// A Slurm array job script, one array task per run.
    Slurm,
}

/// A matrix file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MatrixFile {
    /// The experiment config every run starts from, relative to the matrix file.
    pub base: PathBuf,
    /// The algorithms.
    pub algos: Vec<AlgoKind>,
    /// The tracks.
    pub tracks: Vec<String>,
    /// The rival counts.
    pub rivals: Vec<usize>,
    /// The training seeds.
    pub seeds: Vec<u64>,
    /// An experiment-config fragment laid over the base for every run (before `algo`'s).
    #[serde(default)]
    pub experiment: toml::Table,
    /// Per algorithm (by name), an experiment-config fragment laid over the base.
    #[serde(default)]
    pub algo: BTreeMap<String, toml::Table>,
    /// How the runs are trained.
    #[serde(default)]
    pub train: SweepTrain,
    /// How the runs are evaluated.
    #[serde(default)]
    pub eval: SweepEval,
    /// The context ablation after each context-aware run's evaluation (none by default).
    #[serde(default)]
    pub ablation: Option<SweepAblation>,
}

/// The context ablation of a sweep (H6 of docs/table2/README.md): every cRSSM and cMask run
/// evaluated again under `[eval]`'s protocol with `laps` laps a context, told each context of
/// `told`, and every cMask run with its mask fixed at each of `masks`; each in
/// `<run>/ablation/<condition>`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepAblation {
    /// Laps per context (the main evaluation's first laps share their episode seeds).
    pub laps: usize,
    /// What cRSSM and cMask are told instead of the context: `zeros`, `other`.
    #[serde(default)]
    pub told: Vec<ToldContext>,
    /// The masks cMask is fixed at, `[m_v, m_θ]` in [0, 1].
    #[serde(default)]
    pub masks: Vec<[f32; 2]>,
}

/// One evaluation of a run: the protocol's, or one condition of the context ablation.
#[derive(Clone, Debug, PartialEq)]
struct EvalPass {
    /// Its output folder.
    dir: PathBuf,
    /// Laps per context.
    laps: usize,
    /// What the agent is told.
    told: ToldContext,
    /// cMask's fixed mask.
    mask: Option<[f32; 2]>,
}

/// How a sweep trains its runs.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepTrain {
    /// Actor processes per run; 0 trains inline (one process, continued exactly from its
    /// resume point if interrupted).
    pub actors: usize,
}

impl Default for SweepTrain {
    fn default() -> Self {
        Self { actors: 1 }
    }
}

/// How a sweep evaluates its runs (the paper's protocol by default).
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepEval {
    /// Grid points per context dimension.
    pub grid: usize,
    /// Half-width of the context grid.
    pub range: f64,
    /// Laps per context.
    pub laps: usize,
    /// Checkpoint evaluated: best, latest or step-N.
    pub checkpoint: String,
    /// How the agent acts.
    pub act: ActMode,
    /// Seed of the evaluation episodes.
    pub seed: u64,
    /// Race only these contexts of the grid, as `ctxrace eval --contexts` takes them (e.g.
    /// `"17-48"`, the paper's code's test contexts) [default: all].
    pub contexts: Option<String>,
}

impl Default for SweepEval {
    fn default() -> Self {
        use ctxrace_sim::eval_dir::{GRID, LAPS, RANGE};
        Self {
            grid: GRID,
            range: RANGE,
            laps: LAPS,
            checkpoint: ctxrace_run::trained::CheckpointChoice::default().to_string(),
            act: ActMode::default(),
            seed: 0,
            contexts: None,
        }
    }
}

impl SweepEval {
    /// The grid indices its `contexts` selects (none: the whole grid).
    fn chosen(&self) -> Result<Option<Vec<usize>>> {
        Ok(self
            .contexts
            .as_deref()
            .map(|spec| ctxrace_sim::eval_dir::parse_contexts(spec, self.grid * self.grid))
            .transpose()?)
    }
}

/// One run of a matrix.
#[derive(Clone, Debug)]
pub struct MatrixRun {
    /// Its name and directory name.
    pub name: String,
    /// Its resolved experiment.
    pub config: ExperimentConfig,
}

impl MatrixFile {
    /// Reads a matrix file; errors name the file and the key.
    pub fn load(path: &Path) -> Result<Self> {
        let text = read_config_text(path).context("reading the matrix")?;
        let m: Self = toml::from_str(&text).map_err(|e| {
            anyhow::anyhow!("parsing matrix {}: {}", path.display(), toml_message(&e))
        })?;
        for (axis, empty) in [
            ("algos", m.algos.is_empty()),
            ("tracks", m.tracks.is_empty()),
            ("rivals", m.rivals.is_empty()),
            ("seeds", m.seeds.is_empty()),
        ] {
            if empty {
                bail!("matrix {}: {axis} lists no value", path.display());
            }
        }
        for name in m.algo.keys() {
            if name.parse::<AlgoKind>().is_err() {
                bail!(
                    "matrix {}: [algo.{name}] names no algorithm (sac, dreamerv3, crssm, cmask)",
                    path.display()
                );
            }
        }
        m.eval
            .checkpoint
            .parse::<ctxrace_run::trained::CheckpointChoice>()
            .map_err(|e| anyhow::anyhow!("matrix {}: [eval] checkpoint: {e}", path.display()))?;
        m.eval
            .chosen()
            .with_context(|| format!("matrix {}: [eval] contexts", path.display()))?;
        if let Some(a) = &m.ablation {
            if a.laps == 0 || a.laps > m.eval.laps {
                bail!(
                    "matrix {}: [ablation] laps = {} must lie in 1..={} ([eval] laps: its \
                     baseline is the main evaluation's first laps)",
                    path.display(),
                    a.laps,
                    m.eval.laps
                );
            }
            if a.told.contains(&ToldContext::True) {
                bail!(
                    "matrix {}: [ablation] told lists \"true\", the main evaluation; use \
                     \"zeros\" or \"other\"",
                    path.display()
                );
            }
            if let Some(m) = a
                .masks
                .iter()
                .find(|m| !m.iter().all(|v| (0.0..=1.0).contains(v)))
            {
                bail!(
                    "matrix {}: [ablation] masks holds {m:?}; each value must lie in [0, 1]",
                    path.display()
                );
            }
        }
        Ok(m)
    }

    /// The evaluations of `run` (its folder `dir`): the protocol's in `dir/eval`, then for a
    /// context-aware agent each condition of the ablation in `dir/ablation/<condition>`.
    fn passes(&self, run: &MatrixRun, dir: &Path) -> Vec<EvalPass> {
        let mut passes = vec![EvalPass {
            dir: dir.join("eval"),
            laps: self.eval.laps,
            told: ToldContext::True,
            mask: None,
        }];
        let mode = run.config.agent.algo.context_mode();
        if let (Some(a), true) = (&self.ablation, mode != ContextMode::None) {
            let condition = |name: String| dir.join("ablation").join(name);
            for &told in &a.told {
                let name = told.to_possible_value().map(|v| v.get_name().to_string());
                passes.push(EvalPass {
                    dir: condition(name.unwrap_or_default()),
                    laps: a.laps,
                    told,
                    mask: None,
                });
            }
            if mode == ContextMode::Cmask {
                for &[v, t] in &a.masks {
                    passes.push(EvalPass {
                        dir: condition(format!("mask-{v}-{t}")),
                        laps: a.laps,
                        told: ToldContext::True,
                        mask: Some([v, t]),
                    });
                }
            }
        }
        passes
    }

    /// Whether every evaluation of `run` (in `dir`) is complete.
    fn is_evaluated(&self, run: &MatrixRun, dir: &Path) -> bool {
        self.passes(run, dir)
            .iter()
            .all(|pass| is_evaluated(pass, &self.eval))
    }

    /// Every run, algorithm-major (`algos` × `tracks` × `rivals` × the first `seeds` seeds),
    /// keeping those that `only` admits. `dir` is the matrix file's folder (for `base`).
    pub fn runs(&self, dir: &Path, seeds: Option<usize>, only: &Only) -> Result<Vec<MatrixRun>> {
        let base_path = dir.join(&self.base);
        let base_text = read_config_text(&base_path).context("reading the matrix's base")?;
        let base: toml::Table = toml::from_str(&base_text).map_err(|e| {
            anyhow::anyhow!("parsing {}: {}", base_path.display(), toml_message(&e))
        })?;
        let seeds = &self.seeds[..seeds.unwrap_or(self.seeds.len()).min(self.seeds.len())];
        let mut runs = Vec::new();
        let base = ctxrace_config::preset::merge_tables(base, self.experiment.clone());
        for &algo in &self.algos {
            let mut table = base.clone();
            if let Some(over) = self.algo.get(algo.name()) {
                table = ctxrace_config::preset::merge_tables(table, over.clone());
            }
            for track in &self.tracks {
                for &rivals in &self.rivals {
                    for &seed in seeds {
                        let axes = [
                            ("algo", algo.name().to_string()),
                            ("track", track.clone()),
                            ("rivals", rivals.to_string()),
                            ("seed", seed.to_string()),
                        ];
                        if !only.admits(&axes) {
                            continue;
                        }
                        let config = resolve(&table, algo, track, rivals, seed)
                            .with_context(|| format!("the run {algo} {track} {rivals}r s{seed}"))?;
                        runs.push(MatrixRun {
                            name: ctxrace_run::run_dir::run_name(&config),
                            config,
                        });
                    }
                }
            }
        }
        Ok(runs)
    }
}

/// The experiment of one run: `table` with the run's axis values set.
fn resolve(
    table: &toml::Table,
    algo: AlgoKind,
    track: &str,
    rivals: usize,
    seed: u64,
) -> Result<ExperimentConfig> {
    let text = toml::to_string(table)?;
    let mut cfg = ExperimentConfig::from_toml(&text, "the matrix's base")?;
    cfg.agent.algo = algo;
    cfg.track = track.to_string();
    cfg.race.rivals = rivals;
    cfg.train.seed = seed;
    cfg.agent.set_seed(seed);
    cfg.validate()?;
    Ok(cfg)
}

/// A `--only` filter: for each named axis, the values admitted.
#[derive(Clone, Debug, Default)]
pub struct Only(BTreeMap<String, Vec<String>>);

impl std::str::FromStr for Only {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let mut only = BTreeMap::<String, Vec<String>>::new();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let Some((key, value)) = part.split_once('=') else {
                return Err(format!(
                    "--only: '{part}' is not AXIS=VALUE, e.g. algo=cmask"
                ));
            };
            if !["algo", "track", "rivals", "seed"].contains(&key) {
                return Err(format!(
                    "--only: '{key}' is no axis; use algo, track, rivals or seed"
                ));
            }
            only.entry(key.into()).or_default().push(value.into());
        }
        Ok(Self(only))
    }
}

impl Only {
    /// Whether a run with these axis values passes.
    fn admits(&self, axes: &[(&str, String)]) -> bool {
        axes.iter()
            .all(|(k, v)| self.0.get(*k).is_none_or(|vals| vals.contains(v)))
    }
}

/// Runs `ctxrace sweep`.
pub fn run(args: SweepArgs) -> Result<()> {
    let matrix = MatrixFile::load(&args.matrix)?;
    let only: Only = match &args.only {
        Some(s) => s.parse().map_err(anyhow::Error::msg)?,
        None => Only::default(),
    };
    let dir = args.matrix.parent().unwrap_or(Path::new("."));
    let mut runs = matrix.runs(dir, args.seeds, &only)?;
    if runs.is_empty() {
        bail!("the matrix has no run that --only admits");
    }
    let out = match &args.out {
        Some(o) => o.clone(),
        None => {
            let stem = args
                .matrix
                .file_stem()
                .and_then(|s| s.to_str())
                .unwrap_or("sweep");
            PathBuf::from("runs").join(stem)
        }
    };
    if args.jobs == 0 {
        bail!("--jobs must be at least 1");
    }
    let cores = args.cores.unwrap_or_else(|| {
        let all = std::thread::available_parallelism().map_or(1, |n| n.get());
        (all / args.jobs).max(1)
    });
    if let Some(name) = &args.run {
        let Some(run) = runs.iter().find(|r| &r.name == name) else {
            bail!(
                "the matrix has no run {name}; its runs are {}",
                runs.iter()
                    .map(|r| r.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        };
        return run_one(&matrix, run, &out, cores, args.tracks_dir.as_deref());
    }
    if args.report {
        let missing: Vec<&str> = runs
            .iter()
            .filter(|r| !matrix.is_evaluated(r, &out.join(&r.name)))
            .map(|r| r.name.as_str())
            .collect();
        if !missing.is_empty() {
            bail!(
                "--report: {} of {} runs are not evaluated yet in {}: {}; run the sweep (or \
                 its array tasks) to the end first",
                missing.len(),
                runs.len(),
                out.display(),
                missing.join(", ")
            );
        }
        return write_report(&out, &runs, args.tracks_dir.as_deref());
    }
    if let Some(emit) = args.emit {
        let text = emit_commands(emit, &args, &runs, &out, cores)?;
        print!("{text}");
        return Ok(());
    }
    let _lock = DirLock::acquire(&out)?;
    runs.retain(|r| !matrix.is_evaluated(r, &out.join(&r.name)));
    let done_before = matrix.runs(dir, args.seeds, &only)?.len() - runs.len();
    schedule(&args, &runs, done_before, &out, cores)?;
    let all = matrix.runs(dir, args.seeds, &only)?;
    if all
        .iter()
        .all(|r| matrix.is_evaluated(r, &out.join(&r.name)))
    {
        write_report(&out, &all, args.tracks_dir.as_deref())?;
    }
    Ok(())
}

/// Whether `pass` of the sweep's protocol `eval` is complete.
fn is_evaluated(pass: &EvalPass, eval: &SweepEval) -> bool {
    let eval_dir = &pass.dir;
    let Ok(meta) = ctxrace_run::results::read_json::<ctxrace_sim::evaluation::EvalMeta>(
        &eval_dir.join("meta.json"),
    ) else {
        return false;
    };
    eval_dir.join("contexts.csv").is_file()
        && (meta.grid, meta.laps, meta.seed, meta.act)
            == (eval.grid, pass.laps, eval.seed, eval.act)
        && (meta.told, meta.mask) == (pass.told, pass.mask)
        && meta.range == eval.range
        && meta.checkpoint == eval.checkpoint
        && eval.chosen().is_ok_and(|chosen| chosen == meta.contexts)
}

/// Trains (or resumes) and evaluates one run in `<out>/<name>`, with `cores` cores. A stop
/// signal reaches the children too (they share the process group); this waits for them.
fn run_one(
    matrix: &MatrixFile,
    run: &MatrixRun,
    out: &Path,
    cores: usize,
    tracks_dir: Option<&Path>,
) -> Result<()> {
    let stop = ctxrace_ipc::termination_flag()?;
    let configs = out.join("configs");
    std::fs::create_dir_all(&configs).with_context(|| format!("creating {}", configs.display()))?;
    let config_path = configs.join(format!("{}.toml", run.name));
    let text = run.config.to_toml()?;
    ctxrace_run::run_dir::write_atomic(&config_path, text.as_bytes())
        .with_context(|| format!("writing {}", config_path.display()))?;
    let dir = out.join(&run.name);
    let exe = std::env::current_exe().context("locating the ctxrace binary")?;
    let a = matrix.train.actors;
    let threads = if a == 0 {
        cores
    } else {
        cores.saturating_sub(a).max(1)
    };
    let mut train = Command::new(&exe);
    train
        .arg("train")
        .arg(&config_path)
        .arg("--run-dir")
        .arg(&dir)
        .args(["--resume", "--threads", &threads.to_string()]);
    if a == 0 {
        train.arg("--inline");
    } else {
        train.args(["--actors", &a.to_string()]);
    }
    pass_tracks_dir(&mut train, tracks_dir);
    wait_for(train, &format!("training {}", run.name))?;
    if stop.load(Ordering::Relaxed) {
        bail!("interrupted while training {}", run.name);
    }
    let e = &matrix.eval;
    let name = |v: Option<clap::builder::PossibleValue>| v.map(|v| v.get_name().to_string());
    for pass in matrix.passes(run, &dir) {
        if is_evaluated(&pass, e) {
            continue;
        }
        let mut eval = Command::new(&exe);
        eval.arg("eval").arg(&dir).arg("--out").arg(&pass.dir);
        eval.args([
            "--grid",
            &e.grid.to_string(),
            "--range",
            &e.range.to_string(),
        ]);
        eval.args([
            "--laps",
            &pass.laps.to_string(),
            "--seed",
            &e.seed.to_string(),
        ]);
        eval.args([
            "--checkpoint",
            &e.checkpoint,
            "--workers",
            &cores.to_string(),
        ]);
        eval.arg("--act").args(name(e.act.to_possible_value()));
        eval.arg("--told-context")
            .args(name(pass.told.to_possible_value()));
        if let Some([v, t]) = pass.mask {
            eval.args(["--mask", &format!("{v},{t}")]);
        }
        if let Some(contexts) = &e.contexts {
            eval.args(["--contexts", contexts]);
        }
        pass_tracks_dir(&mut eval, tracks_dir);
        let what = format!("evaluating {} ({})", run.name, pass.dir.display());
        wait_for(eval, &what)?;
        if stop.load(Ordering::Relaxed) {
            bail!("interrupted while {what}");
        }
    }
    Ok(())
}

/// Gives `cmd` (a `ctxrace` command) the sweep's tracks folder, if it names one.
fn pass_tracks_dir(cmd: &mut Command, tracks_dir: Option<&Path>) {
    if let Some(d) = tracks_dir {
        cmd.arg("--tracks-dir").arg(d);
    }
}

/// Runs `cmd` to its end (it dies with this process); an error names `what` when it fails.
fn wait_for(mut cmd: Command, what: &str) -> Result<()> {
    die_with_parent(&mut cmd);
    let status = cmd
        .status()
        .with_context(|| format!("starting the process {what}"))?;
    if !status.success() {
        bail!("{what} failed ({status})");
    }
    Ok(())
}

/// Runs the `pending` runs, at most `--jobs` at once, each as `ctxrace sweep MATRIX --run NAME`
/// in its own process group, with one progress bar for the sweep.
fn schedule(
    args: &SweepArgs,
    pending: &[MatrixRun],
    done_before: usize,
    out: &Path,
    cores: usize,
) -> Result<()> {
    let logs = out.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    let total = (done_before + pending.len()) as u64;
    let bar = crate::progress::progress_bar(total, "runs");
    bar.set_position(done_before as u64);
    let stop = ctxrace_ipc::termination_flag()?;
    let start = Instant::now();
    let mut queue: std::collections::VecDeque<&MatrixRun> = pending.iter().collect();
    let mut running: Vec<(String, Child)> = Vec::new();
    let (mut finished, mut failed, mut signalled) = (0usize, Vec::new(), false);
    let exe = std::env::current_exe().context("locating the ctxrace binary")?;
    loop {
        while running.len() < args.jobs && !stop.load(Ordering::Relaxed) {
            let Some(run) = queue.pop_front() else { break };
            let log = logs.join(format!("{}.log", run.name));
            let file = ctxrace_run::run_dir::open_append(&log)
                .with_context(|| format!("opening {}", log.display()))?;
            let mut cmd = Command::new(&exe);
            cmd.args(own_command(args, &run.name, out, cores))
                .stdout(file.try_clone()?)
                .stderr(file)
                .stdin(Stdio::null())
                .process_group(0);
            die_with_parent(&mut cmd);
            let child = cmd
                .spawn()
                .with_context(|| format!("starting the run {}", run.name))?;
            running.push((run.name.clone(), child));
        }
        if running.is_empty() {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
        if stop.load(Ordering::Relaxed) && !signalled {
            signalled = true;
            for (_, child) in &running {
                // SAFETY: signals the run's own process group (its pid, from process_group(0)).
                unsafe {
                    libc::kill(-(child.id() as libc::pid_t), libc::SIGTERM);
                }
            }
        }
        let mut still = Vec::new();
        for (name, mut child) in running {
            match child.try_wait()? {
                Some(status) if status.success() => finished += 1,
                Some(status) => failed.push(format!("{name} ({status})")),
                None => still.push((name, child)),
            }
        }
        running = still;
        let done = done_before + finished;
        bar.set_position(done as u64);
        let eta = if finished > 0 {
            let per_run = start.elapsed().as_secs_f64() / finished as f64;
            let left = (queue.len() + running.len()) as f64 / args.jobs as f64;
            format!(", ETA {}", hms(per_run * left))
        } else {
            String::new()
        };
        bar.set_message(format!(
            "| {done} done, {} running, {} queued, {} failed{eta}",
            running.len(),
            queue.len(),
            failed.len()
        ));
    }
    bar.finish();
    if stop.load(Ordering::Relaxed) {
        bail!(
            "interrupted: {} runs left; rerun the same command to continue",
            queue.len() + failed.len()
        );
    }
    if !failed.is_empty() {
        bail!(
            "{} runs failed: {}; see {}/<run>.log, then rerun the same command",
            failed.len(),
            failed.join(", "),
            logs.display()
        );
    }
    Ok(())
}

/// `secs` as `h:mm:ss`.
fn hms(secs: f64) -> String {
    let s = secs.max(0.0).round() as u64;
    format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
}

/// The arguments of the `ctxrace` command that runs `name` of this sweep alone (`--run NAME`
/// last).
fn own_command(args: &SweepArgs, name: &str, out: &Path, cores: usize) -> Vec<String> {
    let mut v = sweep_words(args, out, cores);
    v.extend(["--run".into(), name.to_string()]);
    v
}

/// The arguments every `ctxrace sweep` command of this sweep starts with: the matrix, the
/// output folder, the cores, the seeds and the tracks folder.
fn sweep_words(args: &SweepArgs, out: &Path, cores: usize) -> Vec<String> {
    let mut v = vec![
        "sweep".to_string(),
        args.matrix.display().to_string(),
        "--out".into(),
        out.display().to_string(),
        "--cores".into(),
        cores.to_string(),
    ];
    if let Some(k) = args.seeds {
        v.extend(["--seeds".into(), k.to_string()]);
    }
    if let Some(d) = &args.tracks_dir {
        v.extend(["--tracks-dir".into(), d.display().to_string()]);
    }
    v
}

/// `p` made absolute, refused when it is not UTF-8 (an emitted script could not name it).
fn absolute_utf8(p: &Path, what: &str) -> Result<PathBuf> {
    let abs =
        std::path::absolute(p).with_context(|| format!("resolving the {what} {}", p.display()))?;
    if abs.to_str().is_none() {
        bail!(
            "the {what} {} is not valid UTF-8, which an emitted command cannot name; rename \
             it or choose another",
            abs.display()
        );
    }
    Ok(abs)
}

/// The `--emit` text: one command per run, or a script submitting them to Slurm. Every path in
/// it (binary, matrix, output, tracks folder) is absolute, so that it runs from any folder.
fn emit_commands(
    emit: Emit,
    args: &SweepArgs,
    runs: &[MatrixRun],
    out: &Path,
    cores: usize,
) -> Result<String> {
    let exe = std::env::current_exe().context("locating the ctxrace binary")?;
    let exe = absolute_utf8(&exe, "ctxrace binary")?;
    // the tracks folder this sweep sees now, whatever folder or environment runs the commands
    let tracks = args
        .tracks_dir
        .clone()
        .unwrap_or_else(ctxrace_tracks::files::default_tracks_dir);
    let sweep = SweepArgs {
        matrix: absolute_utf8(&args.matrix, "matrix")?,
        seeds: args.seeds,
        jobs: 1,
        only: None,
        out: None,
        emit: None,
        run: None,
        cores: Some(cores),
        tracks_dir: Some(absolute_utf8(&tracks, "tracks folder")?),
        report: false,
        slurm: Default::default(),
    };
    let out = absolute_utf8(out, "output folder")?;
    let quoted = |words: Vec<String>| {
        std::iter::once(exe.display().to_string())
            .chain(words)
            .map(|a| shell_quote(&a))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let prefix = quoted(sweep_words(&sweep, &out, cores)) + " --run";
    Ok(match emit {
        Emit::List => runs
            .iter()
            .map(|r| format!("{prefix} {}\n", shell_quote(&r.name)))
            .collect(),
        Emit::Slurm => {
            if let Some(c) = out.to_str().and_then(|o| o.chars().find(|c| !is_plain(*c))) {
                bail!(
                    "--out {}: Slurm's #SBATCH --output line cannot quote {c:?}; choose an \
                     output folder of letters, digits and -_./:=,+@",
                    out.display()
                );
            }
            let mut report = sweep_words(&sweep, &out, cores);
            report.push("--report".into());
            let names: Vec<String> = runs.iter().map(|r| r.name.clone()).collect();
            crate::slurm::script(
                &args.slurm,
                &crate::slurm::SlurmSweep {
                    stem: sweep
                        .matrix
                        .file_stem()
                        .and_then(|s| s.to_str())
                        .unwrap_or("sweep"),
                    matrix: &sweep.matrix,
                    out: &out,
                    runs: &names,
                    cores,
                    run_command: &prefix,
                    report_command: &quoted(report),
                },
            )?
        }
    })
}

/// Writes `<out>/report/` over every run's evaluation (its figures read the tracks in
/// `tracks_dir`, when given).
fn write_report(out: &Path, runs: &[MatrixRun], tracks_dir: Option<&Path>) -> Result<()> {
    let exe = std::env::current_exe().context("locating the ctxrace binary")?;
    let mut report = Command::new(exe);
    report.arg("report");
    for r in runs {
        report.arg(out.join(&r.name));
    }
    report
        .arg("--out")
        .arg(out.join("report"))
        .stdout(Stdio::null());
    pass_tracks_dir(&mut report, tracks_dir);
    wait_for(report, "writing the report")?;
    println!(
        "{} runs evaluated; report in {}",
        runs.len(),
        out.join("report").display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn matrix(dir: &Path) -> MatrixFile {
        std::fs::write(
            dir.join("base.toml"),
            "[race]\nrivals = 1\n[agent]\nalgo = \"sac\"\n[train]\nenv_steps = 500\nprefill = 100\n",
        )
        .unwrap();
        let text = r#"base = "base.toml"
algos = ["sac", "cmask"]
tracks = ["f1_esp", "generated:3"]
rivals = [1, 3]
seeds = [10000, 10010, 10020]
[algo.sac.train]
train_ratio = 2.0
"#;
        std::fs::write(dir.join("m.toml"), text).unwrap();
        MatrixFile::load(&dir.join("m.toml")).unwrap()
    }

    #[test]
    fn the_matrix_expands_to_named_runs_with_their_overrides() {
        let dir = tempfile::tempdir().unwrap();
        let m = matrix(dir.path());
        let runs = m.runs(dir.path(), None, &Only::default()).unwrap();
        assert_eq!(runs.len(), 2 * 2 * 2 * 3);
        assert_eq!(runs[0].name, "sac-f1_esp-1r-s10000");
        assert_eq!(runs.last().unwrap().name, "cmask-generated_3-3r-s10020");
        let names: std::collections::HashSet<_> = runs.iter().map(|r| &r.name).collect();
        assert_eq!(names.len(), runs.len(), "names are unique");
        for r in &runs {
            let want = match r.config.agent.algo {
                AlgoKind::Sac => 2.0,
                AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => 1.0,
            };
            assert_eq!(r.config.train.train_ratio, want, "{}", r.name);
            assert_eq!(r.config.train.env_steps, 500);
            assert_eq!(r.config.agent.seed(), r.config.train.seed);
        }
        let only: Only = "algo=cmask,rivals=3,seed=10000,seed=10020".parse().unwrap();
        let some = m.runs(dir.path(), Some(2), &only).unwrap();
        let names: Vec<_> = some.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            ["cmask-f1_esp-3r-s10000", "cmask-generated_3-3r-s10000"]
        );
        assert!("algo".parse::<Only>().unwrap_err().contains("AXIS=VALUE"));
        assert!("colour=red"
            .parse::<Only>()
            .unwrap_err()
            .contains("no axis"));
    }

    #[test]
    fn the_ablation_evaluates_context_aware_runs_again_under_each_condition() {
        let dir = tempfile::tempdir().unwrap();
        let m = matrix(dir.path());
        let text = std::fs::read_to_string(dir.path().join("m.toml")).unwrap();
        let with = |extra: &str| {
            std::fs::write(dir.path().join("a.toml"), format!("{text}{extra}")).unwrap();
            MatrixFile::load(&dir.path().join("a.toml"))
        };
        let a = with(
            "[ablation]\nlaps = 20\ntold = [\"zeros\", \"other\"]\nmasks = [[1, 0], [0.5, 1]]\n",
        )
        .unwrap();
        let runs = a.runs(dir.path(), Some(1), &Only::default()).unwrap();
        let run_dir = Path::new("out/r");
        let sac = runs
            .iter()
            .find(|r| r.config.agent.algo == AlgoKind::Sac)
            .unwrap();
        let cmask = runs
            .iter()
            .find(|r| r.config.agent.algo == AlgoKind::Cmask)
            .unwrap();
        assert_eq!(a.passes(sac, run_dir), m.passes(sac, run_dir));
        let passes = a.passes(cmask, run_dir);
        let dirs: Vec<_> = passes.iter().map(|p| p.dir.to_str().unwrap()).collect();
        assert_eq!(
            dirs,
            [
                "out/r/eval",
                "out/r/ablation/zeros",
                "out/r/ablation/other",
                "out/r/ablation/mask-1-0",
                "out/r/ablation/mask-0.5-1"
            ]
        );
        assert_eq!((passes[0].laps, passes[1].laps), (50, 20));
        assert_eq!(passes[2].told, ToldContext::Other);
        assert_eq!(passes[4].mask, Some([0.5, 1.0]));
        for (extra, says) in [
            ("[ablation]\nlaps = 0\n", "laps = 0 must lie in 1..=50"),
            ("[ablation]\nlaps = 60\n", "laps = 60 must lie in 1..=50"),
            (
                "[ablation]\nlaps = 5\ntold = [\"true\"]\n",
                "use \"zeros\" or \"other\"",
            ),
            (
                "[ablation]\nlaps = 5\nmasks = [[2, 0]]\n",
                "must lie in [0, 1]",
            ),
            (
                "[ablation]\nlaps = 5\ntold = [\"none\"]\n",
                "unknown variant",
            ),
        ] {
            let err = format!("{:#}", with(extra).unwrap_err());
            assert!(err.contains(says), "{extra}: {err}");
        }
    }

    #[test]
    fn the_shipped_paper_matrix_holds_its_80_runs() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/paper/matrix.toml");
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        assert_eq!(runs.len(), 80);
        let cmask = runs
            .iter()
            .find(|r| r.name == "cmask-f1_gbr-3r-s10040")
            .unwrap();
        assert_eq!(cmask.config.train.env_steps, 100_000);
        assert_eq!(cmask.config.train.train_ratio, 1.0);
        let sac = runs
            .iter()
            .find(|r| r.name == "sac-f1_esp-1r-s10000")
            .unwrap();
        assert_eq!(
            (
                sac.config.train.train_ratio,
                sac.config.agent.sac.batch_size
            ),
            (2.0, 100)
        );
        assert_eq!(
            (m.eval.grid, m.eval.laps, m.eval.act),
            (7, 50, ActMode::Sample)
        );
    }

    #[test]
    fn the_shipped_reduced_matrix_keeps_the_protocol() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/paper/reduced.toml");
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        assert_eq!(runs.len(), 8);
        assert_eq!((m.eval.grid, m.eval.range, m.eval.laps), (7, 0.3, 50));
        assert!(runs.iter().all(|r| r.config.train.context_range == 0.15));
    }

    #[test]
    fn bad_matrices_name_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let write = |text: &str| {
            let p = dir.path().join("bad.toml");
            std::fs::write(&p, text).unwrap();
            format!("{:#}", MatrixFile::load(&p).unwrap_err())
        };
        let axes = "base = \"b.toml\"\nalgos = [\"sac\"]\ntracks = [\"f1_esp\"]\nrivals = [1]\n";
        assert!(write(&format!("{axes}seeds = []\n")).contains("seeds lists no value"));
        assert!(write(&format!("{axes}seeds = [0]\n[algo.sack]\n")).contains("[algo.sack]"));
        assert!(write(&format!("{axes}seeds = [0]\ncolour = 1\n")).contains("colour"));
        assert!(write(&format!(
            "{axes}seeds = [0]\n[eval]\ncheckpoint = \"top\"\n"
        ))
        .contains("checkpoint"));
        let err = write(&format!(
            "{axes}seeds = [0]\n[eval]\ncontexts = \"40-60\"\n"
        ));
        assert!(
            err.contains("[eval] contexts") && err.contains("outside the grid"),
            "{err}"
        );
    }

    #[test]
    fn the_table2_matrix_evaluates_the_papers_protocol() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/paper/table2.toml");
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        // 4 algorithms x 1 and 3 rivals x 5 seeds
        assert_eq!(runs.len(), 40);
        // all 49 contexts of the 7 x 7 grid, 50 laps each, as the paper's text and means
        assert_eq!(m.eval.chosen().unwrap(), None);
        assert_eq!((m.eval.grid, m.eval.laps), (7, 50));
        assert!(runs
            .iter()
            .all(|r| r.config.race.preset == ctxrace_config::RacePreset::PaperCode));
        // the same env-step budget for every algorithm
        assert!(runs
            .iter()
            .all(|r| r.config.train.env_steps == runs[0].config.train.env_steps));
    }

    /// The runs of a shipped matrix file of configs/paper.
    fn paper_matrix(name: &str) -> (MatrixFile, Vec<MatrixRun>) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../configs/paper")
            .join(name);
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        (m, runs)
    }

    #[test]
    fn the_protocol_matrices_lay_their_arms_over_the_tables_experiment() {
        use ctxrace_config::agents::{ImaginationContext, MaskSpace};
        let (_, table) = paper_matrix("table2.toml");
        let table_cmask = &table
            .iter()
            .find(|r| r.config.agent.algo == AlgoKind::Cmask)
            .unwrap()
            .config;
        let (_, more) = paper_matrix("table2-more-seeds.toml");
        assert_eq!(more.len(), 15);
        assert!(more.iter().all(|r| r.config.race.rivals == 1
            && r.config.train.seed >= 10_050
            && r.config.train.env_steps == table_cmask.train.env_steps));
        for (file, runs, alpha) in [
            ("table2-paper-mask.toml", 20, 1.0),
            ("table2-paper-mask-alpha0.05.toml", 5, 0.05),
        ] {
            let (_, arm) = paper_matrix(file);
            assert_eq!(arm.len(), runs, "{file}");
            let base = &table_cmask.race;
            for r in &arm {
                let mask = &r.config.agent.dreamer.mask;
                assert_eq!(mask.mask_space, MaskSpace::PaperCode, "{file}");
                assert_eq!(mask.imagination_context, ImaginationContext::Raw);
                assert_eq!((mask.lr, mask.init_alpha), (3e-5, alpha));
                // the rest of the experiment is the table's
                assert_eq!(r.config.train.env_steps, table_cmask.train.env_steps);
                assert_eq!(r.config.race.preset, base.preset);
            }
        }
        // the long runs: the table's experiment at the code's schedule, the code's mask for cMask
        let (_, long) = paper_matrix("long.toml");
        assert_eq!(long.len(), 6);
        for r in &long {
            let t = &r.config.train;
            assert_eq!((t.env_steps, t.train_ratio), (100_000, 1.0));
            assert_eq!(t.keep_best_at, [25_000, 50_000, 75_000]);
            assert_eq!(r.config.race.rival, table_cmask.race.rival);
            let code_mask = r.config.agent.dreamer.mask.mask_space == MaskSpace::PaperCode;
            assert_eq!(code_mask, r.config.agent.algo == AlgoKind::Cmask);
        }
    }

    #[test]
    fn the_emitted_slurm_script_names_every_path_absolutely() {
        let dir = tempfile::tempdir().unwrap();
        let m = matrix(dir.path());
        let runs = m.runs(dir.path(), Some(1), &Only::default()).unwrap();
        let args = SweepArgs {
            matrix: PathBuf::from("rel/m.toml"),
            seeds: Some(1),
            jobs: 1,
            only: None,
            out: None,
            emit: Some(Emit::Slurm),
            run: None,
            cores: Some(2),
            tracks_dir: Some("tracks".into()),
            report: false,
            slurm: Default::default(),
        };
        let script = emit_commands(Emit::Slurm, &args, &runs, Path::new("out"), 2).unwrap();
        let cwd = std::env::current_dir().unwrap();
        let at = |p: &str| cwd.join(p).display().to_string();
        for needle in [
            format!("mkdir -p {}", at("out/slurm")),
            format!("{} --out {}", at("rel/m.toml"), at("out")),
            format!("--tracks-dir {}", at("tracks")),
            "--run \"${RUNS[$SLURM_ARRAY_TASK_ID]}\"".to_string(),
            "--seeds 1 --tracks-dir".to_string(),
            "--report\nCTXRACE_REPORT".to_string(),
            format!("#SBATCH --array=0-{}", runs.len() - 1),
        ] {
            assert!(script.contains(&needle), "{needle} missing from\n{script}");
        }
        let err = emit_commands(Emit::Slurm, &args, &runs, Path::new("my out"), 2)
            .unwrap_err()
            .to_string();
        assert!(err.contains("cannot quote ' '"), "{err}");
    }
}
