//! The logs of a training run directory: the training metrics, one row per logging interval
//! in `metrics.jsonl` (every key), `metrics.csv` (the keys of the first row, in order) and a
//! TensorBoard event file (every key as a scalar at the row's `grad_steps`) ([`MetricsLog`]);
//! the finished training episodes in `episodes.csv` and, with the run's rates, an event file
//! ([`EpisodeLog`], [`RateMeter`]).

use crate::tensorboard::{EventFileError, EventWriter};
use crate::Metrics;
use ctxrace_run::results::{TrainingEpisode, TrainingMask};
use ctxrace_run::run_dir::{
    open_append, METRICS_CSV, METRICS_JSONL, TRAINING_EPISODES, TRAINING_MASKS,
};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Why a log of the run directory could not be opened or written; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// A log could not be opened for appending.
    #[error("opening {}", .path.display())]
    Open {
        /// The log.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A row could not be written.
    #[error("writing {}", .path.display())]
    Write {
        /// The log.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A row could not be written as JSON.
    #[error("writing {}", .path.display())]
    Json {
        /// The log.
        path: PathBuf,
        /// Why.
        #[source]
        source: serde_json::Error,
    },
    /// A row could not be written as CSV.
    #[error("writing {}", .path.display())]
    Csv {
        /// The log.
        path: PathBuf,
        /// Why.
        #[source]
        source: csv::Error,
    },
    /// The TensorBoard event file.
    #[error(transparent)]
    Events(#[from] EventFileError),
}

/// The outcome of a log operation.
type Result<T> = std::result::Result<T, LogError>;

/// Opens `path` for appending, naming it in the error.
fn append(path: PathBuf) -> Result<(File, PathBuf)> {
    match open_append(&path) {
        Ok(file) => Ok((file, path)),
        Err(source) => Err(LogError::Open { path, source }),
    }
}

/// Appends training-interval rows to `metrics.jsonl`, `metrics.csv` and an event file.
pub struct MetricsLog {
    jsonl: (File, PathBuf),
    csv: (File, PathBuf),
    columns: Option<Vec<String>>,
    events: EventWriter,
}

impl MetricsLog {
    /// Opens (appending) the logs in `run_dir`, with a new event file for the process `role`.
    pub fn open(run_dir: &Path, role: &str) -> Result<Self> {
        let csv_path = run_dir.join(METRICS_CSV);
        let columns = std::fs::read_to_string(&csv_path).ok().and_then(|t| {
            t.lines()
                .next()
                .map(|h| h.split(',').map(String::from).collect())
        });
        Ok(Self {
            jsonl: append(run_dir.join(METRICS_JSONL))?,
            csv: append(csv_path)?,
            columns,
            events: EventWriter::create(run_dir, role)?,
        })
    }

    /// Appends one row. Each line goes to its file in one write, so that a process killed
    /// while logging leaves whole lines (a line written piece by piece could be cut after its
    /// first byte, and its restart's next line appended to that piece).
    pub fn write(&mut self, row: &Metrics) -> Result<()> {
        let (jsonl, jsonl_path) = &mut self.jsonl;
        let mut line = serde_json::to_vec(row).map_err(|source| LogError::Json {
            path: jsonl_path.clone(),
            source,
        })?;
        line.push(b'\n');
        jsonl.write_all(&line).map_err(|source| LogError::Write {
            path: jsonl_path.clone(),
            source,
        })?;
        let (csv, csv_path) = &mut self.csv;
        let mut lines = String::new();
        let columns = match &self.columns {
            Some(c) => c,
            None => {
                let c: Vec<String> = row.keys().cloned().collect();
                lines += &(c.join(",") + "\n");
                self.columns.insert(c)
            }
        };
        let cells: Vec<String> = columns
            .iter()
            .map(|k| row.get(k).map_or(String::new(), |v| v.to_string()))
            .collect();
        lines += &(cells.join(",") + "\n");
        csv.write_all(lines.as_bytes())
            .map_err(|source| LogError::Write {
                path: csv_path.clone(),
                source,
            })?;
        let step = row.get("grad_steps").copied().unwrap_or(0.0) as u64;
        self.events
            .scalars(step, row.iter().map(|(k, v)| (k.as_str(), *v)))?;
        Ok(self.events.flush()?)
    }
}

/// A CSV file appended to row by row (its header written only into an empty file), each row
/// flushed.
struct CsvAppender {
    writer: csv::Writer<std::fs::File>,
    path: PathBuf,
}

impl CsvAppender {
    /// Opens (appending) the CSV file at `path`.
    fn open(path: PathBuf) -> Result<Self> {
        let fresh = std::fs::metadata(&path).map_or(true, |m| m.len() == 0);
        let (file, path) = append(path)?;
        Ok(Self {
            writer: csv::WriterBuilder::new()
                .has_headers(fresh)
                .from_writer(file),
            path,
        })
    }

    /// Appends one row and flushes it.
    fn write(&mut self, row: &impl serde::Serialize) -> Result<()> {
        self.writer.serialize(row).map_err(|source| LogError::Csv {
            path: self.path.clone(),
            source,
        })?;
        self.writer.flush().map_err(|source| LogError::Write {
            path: self.path.clone(),
            source,
        })
    }
}

/// Appends training episodes to `episodes.csv` (cMask's mean masks to `training_masks.csv`)
/// and, with the run's rates, to a TensorBoard event file (scalars `episode/*` and `rate/*`,
/// `replay/*` at the run's env steps).
pub struct EpisodeLog {
    episodes: CsvAppender,
    /// `training_masks.csv`, opened at the first masked episode.
    masks: Option<CsvAppender>,
    run_dir: PathBuf,
    events: EventWriter,
}

impl EpisodeLog {
    /// Opens (appending) `<run_dir>/episodes.csv`, with a new event file for `role`.
    pub fn open(run_dir: &Path, role: &str) -> Result<Self> {
        Ok(Self {
            episodes: CsvAppender::open(run_dir.join(TRAINING_EPISODES))?,
            masks: None,
            run_dir: run_dir.to_path_buf(),
            events: EventWriter::create(run_dir, role)?,
        })
    }

    /// Appends one episode's mean context mask to `training_masks.csv`.
    pub fn write_mask(&mut self, mask: &TrainingMask) -> Result<()> {
        let masks = match &mut self.masks {
            Some(m) => m,
            None => self
                .masks
                .insert(CsvAppender::open(self.run_dir.join(TRAINING_MASKS))?),
        };
        masks.write(mask)
    }

    /// Appends one episode.
    pub fn write(&mut self, episode: &TrainingEpisode) -> Result<()> {
        self.episodes.write(episode)?;
        let flag = |b: bool| f64::from(u8::from(b));
        self.events.scalars(
            episode.env_steps,
            [
                ("episode/progress", episode.progress),
                ("episode/overtakes", f64::from(episode.overtakes)),
                ("episode/a2a", flag(episode.a2a)),
                ("episode/wall_crash", flag(episode.wall_crash)),
                ("episode/return", episode.episode_return),
                ("episode/steps", episode.steps as f64),
            ],
        )?;
        Ok(self.events.flush()?)
    }

    /// Records the run's rates and replay fill at `env_steps`.
    pub fn rates(&mut self, env_steps: u64, rates: &Rates) -> Result<()> {
        self.events.scalars(
            env_steps,
            [
                ("rate/env_steps_per_second", rates.env_steps_per_second),
                ("rate/grad_steps_per_second", rates.grad_steps_per_second),
                ("replay/steps", rates.replay_steps as f64),
                ("replay/fill", rates.replay_fill),
            ],
        )?;
        Ok(self.events.flush()?)
    }
}

/// What [`EpisodeLog::rates`] records.
#[derive(Clone, Copy, Debug, Default)]
pub struct Rates {
    /// Environment steps per second since the last record.
    pub env_steps_per_second: f64,
    /// Gradient steps per second since the last record.
    pub grad_steps_per_second: f64,
    /// Steps the replay holds.
    pub replay_steps: u64,
    /// Its fill, `[0, 1]`.
    pub replay_fill: f64,
}

/// Seconds between two [`Rates`] records.
pub const RATES_EVERY: Duration = Duration::from_secs(5);

/// Turns counters into [`Rates`] over the time since the previous reading; the first reading
/// only sets the baseline (a resumed run's counters do not start at zero).
#[derive(Clone, Debug, Default)]
pub struct RateMeter {
    last: Option<(Instant, u64, u64)>,
}

impl RateMeter {
    /// The rates since the last reading when [`RATES_EVERY`] has passed since it, else `None`.
    pub fn read(&mut self, env_steps: u64, grad_steps: u64, replay: (u64, u64)) -> Option<Rates> {
        let Some((at, env_before, grad_before)) = self.last else {
            self.last = Some((Instant::now(), env_steps, grad_steps));
            return None;
        };
        let secs = at.elapsed().as_secs_f64();
        if secs < RATES_EVERY.as_secs_f64() {
            return None;
        }
        let per_second = |now: u64, before: u64| now.saturating_sub(before) as f64 / secs;
        let rates = Rates {
            env_steps_per_second: per_second(env_steps, env_before),
            grad_steps_per_second: per_second(grad_steps, grad_before),
            replay_steps: replay.0,
            replay_fill: replay.0 as f64 / replay.1.max(1) as f64,
        };
        self.last = Some((Instant::now(), env_steps, grad_steps));
        Some(rates)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_keep_the_first_header_across_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let row = |a: f64| Metrics::from([("a".into(), a), ("b".into(), 2.0)]);
        MetricsLog::open(dir.path(), "a")
            .unwrap()
            .write(&row(1.0))
            .unwrap();
        let mut log = MetricsLog::open(dir.path(), "b").unwrap();
        log.write(&Metrics::from([("b".into(), 3.0), ("c".into(), 4.0)]))
            .unwrap();
        let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
        assert_eq!(csv, "a,b\n1,2\n,3\n");
        let jsonl = std::fs::read_to_string(dir.path().join("metrics.jsonl")).unwrap();
        assert_eq!(jsonl.lines().count(), 2);
        assert!(jsonl.contains("\"c\":4.0"));
        let events = crate::tensorboard::event_files(dir.path());
        assert_eq!(events.len(), 2);
        let scalars = crate::tensorboard::read_scalars(&events[1]).unwrap();
        assert_eq!(scalars.len(), 2, "{scalars:?}");
    }
}
