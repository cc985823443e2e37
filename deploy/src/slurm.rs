//! `ctxrace sweep --emit slurm`: a script that submits a sweep to a Slurm cluster as one array
//! job (a task per run, each `ctxrace sweep MATRIX --run NAME`) and a report job that starts
//! once every task succeeded (`--dependency=afterok`).
//!
//! The script is run with `bash` on the submission host, not given to `sbatch`: it first makes
//! the log folder (Slurm opens a task's `--output` file before the task starts, so the folder
//! must exist at submission), then calls `sbatch` twice and says what it submitted. Every path
//! a task needs (the binary, the matrix, the tracks folder, the output folder) is absolute and
//! every option of the run is on its command line, so a task runs the same from any folder and
//! under `--export=NONE`. Arguments given to the script go to both `sbatch` calls (e.g.
//! `bash sweep.sh --export=NONE --qos=long`). Running it again after a task failed or was
//! killed resubmits the sweep: the runs that are done end at once, the others resume.

use anyhow::{bail, Result};
use clap::Args;
use std::fmt::Write as _;
use std::path::Path;

/// The cluster options of `--emit slurm`.
#[derive(Args, Clone, Debug, Default)]
pub struct SlurmArgs {
    /// Slurm partition of the jobs (`--emit slurm`).
    #[arg(long)]
    partition: Option<String>,
    /// Time limit of each array task, as sbatch takes it, e.g. 12:00:00 (`--emit slurm`).
    #[arg(long)]
    time: Option<String>,
    /// Memory of each array task, as sbatch takes it, e.g. 16G (`--emit slurm`).
    #[arg(long)]
    mem: Option<String>,
    /// Account charged for the jobs (`--emit slurm`).
    #[arg(long)]
    account: Option<String>,
    /// Array tasks running at once, the array's `%N` (`--emit slurm`).
    #[arg(long)]
    throttle: Option<usize>,
    /// An extra `#SBATCH` line for the array task, e.g. --sbatch '--qos=long' (repeatable;
    /// `--emit slurm`).
    #[arg(long = "sbatch", value_name = "OPTION", allow_hyphen_values = true)]
    extra: Vec<String>,
}

/// What the script submits: the runs, and the command lines that run one of them and write the
/// report.
pub struct SlurmSweep<'a> {
    /// The job name's suffix (the matrix file's stem).
    pub stem: &'a str,
    /// The matrix file, for the script's header.
    pub matrix: &'a Path,
    /// The sweep's output folder (absolute); the logs go to its `slurm/`.
    pub out: &'a Path,
    /// The runs' names, array task `i` running `runs[i]`.
    pub runs: &'a [String],
    /// Cores per task.
    pub cores: usize,
    /// The command that runs one run, quoted for the shell, the run's name last and left out.
    pub run_command: &'a str,
    /// The command that writes the report, quoted for the shell.
    pub report_command: &'a str,
}

impl SlurmArgs {
    /// Checks the options: each value fits on its `#SBATCH` line.
    fn check(&self) -> Result<()> {
        if self.throttle == Some(0) {
            bail!("--throttle 0 runs no task; give at least 1 (the array tasks running at once)");
        }
        let bad = |v: &str| v.is_empty() || v.contains(['\n', '\r', '\'', '"']);
        let fields = [
            ("partition", &self.partition),
            ("time", &self.time),
            ("mem", &self.mem),
            ("account", &self.account),
        ];
        for (option, value) in fields {
            if let Some(v) = value.as_deref().filter(|v| bad(v)) {
                bail!(
                    "--{option} {v:?}: a Slurm option value is one line without quotes; e.g. \
                     --time 12:00:00, --mem 16G"
                );
            }
        }
        if let Some(v) = self.extra.iter().find(|v| bad(v) || !v.starts_with('-')) {
            bail!(
                "--sbatch {v:?}: give one sbatch option, one line without quotes, each time, \
                 e.g. --sbatch=--qos=long"
            );
        }
        Ok(())
    }

    /// The `#SBATCH` lines of these options for a job; `task` adds those of the array tasks
    /// alone (time, memory, extra lines).
    fn lines(&self, task: bool) -> String {
        let mut s = String::new();
        let mut line = |key: &str, v: &Option<String>| {
            if let Some(v) = v {
                let _ = writeln!(s, "#SBATCH --{key}={v}");
            }
        };
        line("partition", &self.partition);
        line("account", &self.account);
        if task {
            line("time", &self.time);
            line("mem", &self.mem);
            for extra in &self.extra {
                let _ = writeln!(s, "#SBATCH {extra}");
            }
        }
        s
    }
}

/// The submission script of `sweep` under `opts`.
pub fn script(opts: &SlurmArgs, sweep: &SlurmSweep) -> Result<String> {
    opts.check()?;
    let logs = sweep.out.join("slurm");
    let logs_q = crate::shell::shell_quote(&logs.display().to_string());
    let throttle = opts.throttle.map(|n| format!("%{n}")).unwrap_or_default();
    let names: Vec<String> = sweep
        .runs
        .iter()
        .map(|r| crate::shell::shell_quote(r))
        .collect();
    Ok(format!(
        r#"#!/usr/bin/env bash
# ctxrace sweep {matrix}: {n} runs, one Slurm array task each, then a report job.
# Run it with bash on the submission host (not sbatch): `bash <this file> [SBATCH OPTIONS]`;
# its arguments go to both sbatch calls (e.g. --export=NONE). Run it again after a task failed
# or was killed: runs that are done end at once, the others resume. Logs: {logs}/<task>.out
set -euo pipefail
if [[ -n "${{SLURM_JOB_ID:-}}" ]]; then
    echo "run this script with bash, not sbatch: it submits the jobs itself" >&2
    exit 2
fi
# Slurm opens each task's output file at submission: its folder must exist
mkdir -p {logs_q}
array=$(sbatch --parsable "$@" <<'CTXRACE_TASK'
#!/usr/bin/env bash
#SBATCH --job-name=ctxrace-{stem}
#SBATCH --array=0-{last}{throttle}
#SBATCH --cpus-per-task={cores}
#SBATCH --output={logs}/%a.out
{task_lines}set -euo pipefail
RUNS=({names})
exec {run} "${{RUNS[$SLURM_ARRAY_TASK_ID]}}"
CTXRACE_TASK
)
array=${{array%%;*}}
report=$(sbatch --parsable "$@" --dependency=afterok:"$array" <<'CTXRACE_REPORT'
#!/usr/bin/env bash
#SBATCH --job-name=ctxrace-{stem}-report
#SBATCH --cpus-per-task=1
#SBATCH --output={logs}/report.out
{report_lines}set -euo pipefail
exec {report}
CTXRACE_REPORT
)
report=${{report%%;*}}
echo "submitted array job $array ({n} tasks) and report job $report (after all succeed); logs in {logs}"
"#,
        matrix = sweep.matrix.display(),
        n = sweep.runs.len(),
        logs = logs.display(),
        stem = sweep.stem,
        last = sweep.runs.len().saturating_sub(1),
        cores = sweep.cores,
        task_lines = opts.lines(true),
        report_lines = opts.lines(false),
        names = names.join(" "),
        run = sweep.run_command,
        report = sweep.report_command,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sweep<'a>(runs: &'a [String]) -> SlurmSweep<'a> {
        SlurmSweep {
            stem: "m",
            matrix: Path::new("/abs/m.toml"),
            out: Path::new("/abs/out"),
            runs,
            cores: 4,
            run_command: "/bin/ctxrace sweep /abs/m.toml --out /abs/out --run",
            report_command: "/bin/ctxrace sweep /abs/m.toml --out /abs/out --report",
        }
    }

    #[test]
    fn the_script_makes_the_log_folder_before_it_submits_and_chains_the_report() {
        let runs = vec!["a-1r-s0".to_string(), "b-1r-s0".to_string()];
        let opts = SlurmArgs {
            partition: Some("gpu".into()),
            time: Some("2:00:00".into()),
            mem: Some("8G".into()),
            account: Some("lab".into()),
            throttle: Some(3),
            extra: vec!["--qos=long".into()],
        };
        let s = script(&opts, &sweep(&runs)).unwrap();
        let mkdir = s.find("mkdir -p /abs/out/slurm").unwrap();
        assert!(mkdir < s.find("sbatch --parsable").unwrap());
        for line in [
            "#SBATCH --array=0-1%3",
            "#SBATCH --cpus-per-task=4",
            "#SBATCH --output=/abs/out/slurm/%a.out",
            "#SBATCH --partition=gpu",
            "#SBATCH --account=lab",
            "#SBATCH --time=2:00:00",
            "#SBATCH --mem=8G",
            "#SBATCH --qos=long",
            "RUNS=(a-1r-s0 b-1r-s0)",
            "--dependency=afterok:\"$array\"",
            "exec /bin/ctxrace sweep /abs/m.toml --out /abs/out --report",
        ] {
            assert!(s.contains(line), "{line} missing from\n{s}");
        }
        // the report job takes the partition and account, not the tasks' time and memory
        let report = &s[s.find("CTXRACE_REPORT").unwrap()..];
        assert!(report.contains("--partition=gpu") && !report.contains("--mem"));
        let plain = script(&SlurmArgs::default(), &sweep(&runs)).unwrap();
        assert!(plain.contains("#SBATCH --array=0-1\n") && !plain.contains("--partition"));
    }

    #[test]
    fn options_that_would_break_the_script_are_refused_with_the_fix() {
        let runs = vec!["a".to_string()];
        let bad = |opts: SlurmArgs| script(&opts, &sweep(&runs)).unwrap_err().to_string();
        assert!(bad(SlurmArgs {
            throttle: Some(0),
            ..Default::default()
        })
        .contains("at least 1"));
        assert!(bad(SlurmArgs {
            time: Some("1:00\n#SBATCH --x".into()),
            ..Default::default()
        })
        .contains("--time"));
        assert!(bad(SlurmArgs {
            extra: vec!["qos=long".into()],
            ..Default::default()
        })
        .contains("--sbatch=--qos=long"));
    }
}
