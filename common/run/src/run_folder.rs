//! Preparing a run folder for training: which folder (the one given, or
//! `runs/<`[`run_name`]`>` with `-2`, `-3`, … appended when taken), its lock ([`DirLock`]), the
//! resume rule (a folder that holds a run is continued only when asked to, and only if it holds
//! the same experiment), and `config.toml`, the experiment as trained. The launcher, the
//! single-process trainer and any other program that trains prepare their run through here.

use crate::lock::{DirLock, LockError};
use crate::path_error::PathIoError;
use crate::run_dir::{
    run_name, write_atomic, CHECKPOINTS, CONFIG_FILE, METRICS_CSV, METRICS_JSONL, RESUME_DIR,
    TRAINING_EPISODES, TRAINING_MASKS,
};
use ctxrace_config::{ExperimentConfig, ExperimentError};
use std::path::{Path, PathBuf};

/// The folder under which runs are made when none is named.
pub const RUNS_DIR: &str = "runs";

/// Why a run folder could not be prepared.
#[derive(Debug, thiserror::Error)]
pub enum RunFolderError {
    /// The folder is locked by another process.
    #[error(transparent)]
    Lock(#[from] LockError),
    /// The folder holds a run and resuming was not asked for.
    #[error(
        "{} already holds a run; pass another run folder (--run-dir), remove it, or continue \
         it (--resume)",
        .0.display()
    )]
    HoldsARun(PathBuf),
    /// The folder holds another experiment than the one to resume.
    #[error(
        "{} holds another experiment than the one given (compare its {CONFIG_FILE}); pass \
         another run folder (--run-dir)",
        .0.display()
    )]
    OtherExperiment(PathBuf),
    /// Every default name is taken.
    #[error("{RUNS_DIR}/{0} and -2 to -9999 are all taken; name a run folder (--run-dir)")]
    AllTaken(String),
    /// The held experiment could not be read, or the given one not written as TOML.
    #[error(transparent)]
    Experiment(#[from] ExperimentError),
    /// A file of the folder could not be written or removed.
    #[error(transparent)]
    Io(#[from] PathIoError),
}

/// A locked run folder holding the experiment's `config.toml`.
#[derive(Debug)]
pub struct RunFolder {
    /// The folder.
    pub dir: PathBuf,
    /// Its lock, held for as long as the run writes into it.
    pub lock: DirLock,
    /// It held this experiment already (a run to continue).
    pub resumed: bool,
}

impl RunFolder {
    /// Locks the folder of a run of `cfg` and writes the experiment into it: `dir`, which must
    /// not hold a run yet unless `resume` and it holds this experiment; or, without `dir`,
    /// `runs/<`[`run_name`]`>` (with `resume` exactly that, otherwise the first of it and its
    /// `-2`, `-3`, … variants that holds no run). The learner's thread count may differ on
    /// resume: it changes how fast a run trains, not what it computes.
    pub fn prepare(
        cfg: &ExperimentConfig,
        dir: Option<&Path>,
        resume: bool,
    ) -> Result<Self, RunFolderError> {
        let dir = match dir {
            Some(dir) => dir.to_path_buf(),
            None if resume => Path::new(RUNS_DIR).join(run_name(cfg)),
            None => free_run_dir(cfg)?,
        };
        let lock = DirLock::acquire(&dir)?;
        let config = dir.join(CONFIG_FILE);
        let resumed = config.exists();
        if resumed {
            if !resume {
                return Err(RunFolderError::HoldsARun(dir));
            }
            let mut held = ExperimentConfig::load_saved(&config)?;
            held.train.threads = cfg.train.threads;
            if &held != cfg {
                return Err(RunFolderError::OtherExperiment(dir));
            }
        }
        let text = cfg.to_toml()?;
        write_atomic(&config, text.as_bytes()).map_err(PathIoError::at("writing", &config))?;
        Ok(Self { dir, lock, resumed })
    }

    /// Removes what a single-process run wrote (training episodes, metrics, checkpoints, its
    /// resume point): an interrupted one without a usable resume point starts over.
    pub fn start_over(&self) -> Result<(), RunFolderError> {
        for name in [
            TRAINING_EPISODES,
            TRAINING_MASKS,
            METRICS_JSONL,
            METRICS_CSV,
            CHECKPOINTS,
            RESUME_DIR,
        ] {
            let path = self.dir.join(name);
            let removed = if path.is_dir() {
                std::fs::remove_dir_all(&path)
            } else {
                std::fs::remove_file(&path)
            };
            match removed {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(PathIoError::at("removing", &path)(e).into())
                }
                _ => {}
            }
        }
        Ok(())
    }
}

/// `runs/<`[`run_name`]`>`, or the first of its `-2`, `-3`, … variants that holds no run.
fn free_run_dir(cfg: &ExperimentConfig) -> Result<PathBuf, RunFolderError> {
    let base = run_name(cfg);
    let runs = Path::new(RUNS_DIR);
    std::iter::once(runs.join(&base))
        .chain((2..10_000).map(|k| runs.join(format!("{base}-{k}"))))
        .find(|d| !d.join(CONFIG_FILE).exists())
        .ok_or(RunFolderError::AllTaken(base))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_is_resumed_only_when_asked_and_only_with_its_experiment() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("run");
        let cfg = ExperimentConfig::default();
        let first = RunFolder::prepare(&cfg, Some(&dir), false).unwrap();
        assert!(!first.resumed && dir.join(CONFIG_FILE).is_file());
        drop(first);
        let err = RunFolder::prepare(&cfg, Some(&dir), false).unwrap_err();
        assert!(matches!(err, RunFolderError::HoldsARun(_)), "{err}");
        let mut faster = cfg.clone();
        faster.train.threads = Some(7);
        let again = RunFolder::prepare(&faster, Some(&dir), true).unwrap();
        assert!(again.resumed);
        // held while it lives
        let busy = RunFolder::prepare(&faster, Some(&dir), true).unwrap_err();
        assert!(matches!(busy, RunFolderError::Lock(_)), "{busy}");
        drop(again);
        let mut other = cfg.clone();
        other.train.seed += 1;
        let err = RunFolder::prepare(&other, Some(&dir), true).unwrap_err();
        assert!(matches!(err, RunFolderError::OtherExperiment(_)), "{err}");
    }

    #[test]
    fn starting_over_removes_the_single_process_runs_records_only() {
        let tmp = tempfile::tempdir().unwrap();
        let cfg = ExperimentConfig::default();
        let run = RunFolder::prepare(&cfg, Some(tmp.path()), false).unwrap();
        std::fs::write(tmp.path().join(TRAINING_EPISODES), "x").unwrap();
        std::fs::create_dir_all(tmp.path().join(CHECKPOINTS).join("step-1")).unwrap();
        run.start_over().unwrap();
        assert!(!tmp.path().join(TRAINING_EPISODES).exists());
        assert!(!tmp.path().join(CHECKPOINTS).exists());
        assert!(tmp.path().join(CONFIG_FILE).is_file());
        // nothing left to remove is fine
        run.start_over().unwrap();
    }
}
