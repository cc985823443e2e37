//! Training and evaluation results on disk: the rows the trainers and `ctxrace eval` write and
//! `ctxrace report` (or a notebook) reads, and the CSV and JSON readers and writers of a run
//! directory's files (named in [`crate::run_dir`]).
//!
//! A training run directory holds `episodes.csv` with one [`TrainingEpisode`] per finished
//! training episode (the training curves). An evaluation directory (`<run>/eval/` by default)
//! holds the evaluation protocol's records (`ctxrace_actor::evaluation`: `meta.json`,
//! `episodes.csv`, `contexts.csv`, `contexts.json`) and, for cMask agents, `masks.csv.gz`.

use crate::run_dir::write_atomic;
use serde::{de::DeserializeOwned, Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One finished training episode (a point of the training curves).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingEpisode {
    /// Environment steps taken by the whole run when the episode ended.
    pub env_steps: u64,
    /// Gradient steps taken by the learner when the episode ended.
    pub grad_steps: u64,
    /// Actor that ran the episode.
    pub actor: u32,
    /// Episode index within that actor.
    pub episode: u64,
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// PG of the episode.
    pub progress: f64,
    /// OT of the episode.
    pub overtakes: i32,
    /// The episode ended in an ego–rival collision.
    pub a2a: bool,
    /// The episode ended with the ego hitting a wall.
    pub wall_crash: bool,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Decisions taken.
    pub steps: usize,
}

/// cMask's context mask over one training episode: the mean of the masks its policy chose
/// (`training_masks.csv`, a row per episode the policy drove, beside its `episodes.csv` row).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingMask {
    /// Environment steps taken by the run when the episode ended.
    pub env_steps: u64,
    /// Gradient steps taken by the learner when the episode ended.
    pub grad_steps: u64,
    /// Episode index within its actor (as in `episodes.csv`).
    pub episode: u64,
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// Mean mask of `c_v` over the episode's decisions.
    pub mask_speed: f64,
    /// Mean mask of `c_θ` over the episode's decisions.
    pub mask_steer: f64,
    /// Decisions whose mask the means average.
    pub decisions: u64,
}

/// What the replay's current start took of each actor and of the budget
/// ([`crate::run_dir::REPLAY_STREAMS`]), written by the replay each second: its own counts,
/// not what any message claims.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReplayStreams {
    /// Steps stored, by actor id.
    pub stored_by_actor: Vec<u64>,
    /// Steps that arrived after the run's env-step budget was stored, not stored, by actor id.
    pub surplus_by_actor: Vec<u64>,
    /// Chunks rejected, by actor id.
    pub rejected_by_actor: Vec<u64>,
    /// Steps stored in all, those restored from a snapshot included.
    pub inserted: u64,
    /// The run's env-step budget: the replay stores no more.
    pub env_steps: u64,
}

impl ReplayStreams {
    /// Whether the replay has stored the whole budget: no more steps are needed.
    pub fn budget_stored(&self) -> bool {
        self.env_steps > 0 && self.inserted >= self.env_steps
    }
}

/// Why a result file could not be read or written; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    /// The file could not be opened as CSV.
    #[error("opening {}", path.display())]
    Open {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        cause: csv::Error,
    },
    /// A CSV row does not hold the record.
    #[error("{} row {row}", path.display())]
    Row {
        /// The file.
        path: PathBuf,
        /// The row's line number (the header is line 1).
        row: usize,
        /// Why.
        #[source]
        cause: csv::Error,
    },
    /// A record could not be written as CSV.
    #[error(transparent)]
    Csv(#[from] csv::Error),
    /// A value could not be written as JSON.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The file could not be read.
    #[error("reading {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        cause: std::io::Error,
    },
    /// The file does not hold the JSON value.
    #[error("parsing {}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        cause: serde_json::Error,
    },
    /// The file could not be written.
    #[error("writing {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        cause: std::io::Error,
    },
    /// The folder could not be listed.
    #[error("listing {}", path.display())]
    List {
        /// The folder.
        path: PathBuf,
        /// Why.
        #[source]
        cause: std::io::Error,
    },
}

/// Reads every row of a CSV file with a header.
pub fn read_csv<T: DeserializeOwned>(path: &Path) -> Result<Vec<T>, ResultsError> {
    let mut reader = csv::Reader::from_path(path).map_err(|cause| ResultsError::Open {
        path: path.to_path_buf(),
        cause,
    })?;
    reader
        .deserialize()
        .enumerate()
        .map(|(i, row)| {
            row.map_err(|cause| ResultsError::Row {
                path: path.to_path_buf(),
                row: i + 2,
                cause,
            })
        })
        .collect()
}

/// Writes rows as a CSV file with a header, replacing the file atomically
/// ([`write_atomic`]: never through a link planted at its path or its temporary's).
pub fn write_csv<T: Serialize>(path: &Path, rows: &[T]) -> Result<(), ResultsError> {
    let mut writer = csv::Writer::from_writer(Vec::new());
    for row in rows {
        writer.serialize(row)?;
    }
    let write = |cause| ResultsError::Write {
        path: path.to_path_buf(),
        cause,
    };
    let bytes = writer.into_inner().map_err(|e| write(e.into_error()))?;
    write_atomic(path, &bytes).map_err(write)
}

/// Reads a JSON file.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T, ResultsError> {
    let text = std::fs::read_to_string(path).map_err(|cause| ResultsError::Read {
        path: path.to_path_buf(),
        cause,
    })?;
    serde_json::from_str(&text).map_err(|cause| ResultsError::Parse {
        path: path.to_path_buf(),
        cause,
    })
}

/// Writes a value as pretty JSON.
pub fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<(), ResultsError> {
    let text = serde_json::to_string_pretty(value)?;
    // through a temporary file, so that a reader never sees half of it
    write_atomic(path, (text + "\n").as_bytes()).map_err(|cause| ResultsError::Write {
        path: path.to_path_buf(),
        cause,
    })
}

/// The workers' part files of `out` whose names start with `prefix` and end in `.csv`, sorted
/// (result rows `episodes.part-*`, masks `masks.part-*`).
pub fn part_files(out: &Path, prefix: &str) -> Result<Vec<PathBuf>, ResultsError> {
    let listing = std::fs::read_dir(out).map_err(|cause| ResultsError::List {
        path: out.to_path_buf(),
        cause,
    })?;
    let mut parts: Vec<PathBuf> = listing
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(prefix) && n.ends_with(".csv"))
        })
        .collect();
    parts.sort();
    Ok(parts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_round_trip_keeps_every_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("e.csv");
        let episode = |env_steps: u64, wall_crash: bool| TrainingEpisode {
            env_steps,
            grad_steps: env_steps / 2,
            actor: 1,
            episode: 3,
            context_speed: -0.1,
            context_steer: 0.05,
            progress: 0.4,
            overtakes: -1,
            a2a: !wall_crash,
            wall_crash,
            episode_return: 12.5,
            steps: 90,
        };
        let rows = vec![episode(100, true), episode(250, false)];
        write_csv(&path, &rows).unwrap();
        assert_eq!(read_csv::<TrainingEpisode>(&path).unwrap(), rows);
        std::fs::write(&path, "env_steps\nnot a number\n").unwrap();
        let err = read_csv::<TrainingEpisode>(&path).unwrap_err().to_string();
        assert!(err.ends_with("e.csv row 2"), "{err}");
    }

    #[test]
    fn links_planted_at_the_file_or_its_old_temporary_are_not_written_through() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("target");
        std::fs::write(&target, "untouched").unwrap();
        let status = dir.path().join("status.json");
        std::os::unix::fs::symlink(&target, dir.path().join("status.json.tmp")).unwrap();
        write_json(&status, &[1, 2]).unwrap();
        let csv = dir.path().join("contexts.csv");
        std::os::unix::fs::symlink(&target, &csv).unwrap();
        write_csv(&csv, &[(1, 2)]).unwrap();
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "untouched");
        assert_eq!(read_json::<Vec<u32>>(&status).unwrap(), [1, 2]);
        assert!(!csv.symlink_metadata().unwrap().is_symlink());
    }
}
