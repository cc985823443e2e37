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
use ctxrace_run::lock::{die_with_parent, DirLock};
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

mod matrix;

use matrix::is_evaluated;
use matrix::{MatrixFile, MatrixRun, Only};

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
    use matrix::tests::matrix;

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
