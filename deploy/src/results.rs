//! Evaluation and training results on disk: what `ctxrace eval` and the trainers write and what
//! `ctxrace report` reads.
//!
//! An evaluation directory (`<run>/eval/` by default, files named in
//! `ctxrace_common::run_dir`) holds:
//! - `meta.json`: [`EvalMeta`], which agent on which track against how many rivals;
//! - `episodes.csv`: one `EvalEpisode` per evaluation episode (lap);
//! - `contexts.csv` and `contexts.json`: one `ContextSummary` per context of the grid (both
//!   defined, with the metrics, by the protocol in `ctxrace_actor::protocol`).
//! - `masks.csv.gz` (cMask agents): the context mask at every decision (written by the masks module).
//!
//! A training run directory holds `episodes.csv` with one [`TrainingEpisode`] per finished
//! training episode (the training curves).
//!

use anyhow::{Context as _, Result};
use ctxrace_common::run_dir::write_atomic;
use serde::{de::DeserializeOwned, Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// What was evaluated, and how.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalMeta {
    /// Algorithm name (`sac`, `dreamerv3`, `crssm`, `cmask`) or baseline (`random`, `pure-pursuit`).
    pub algo: String,
    /// Track name.
    pub track: String,
    /// Number of rivals.
    pub rivals: usize,
    /// Training seed of the agent (groups runs for seed averaging).
    pub train_seed: u64,
    /// Half-width of the training context range (in-distribution bound).
    pub train_range: f64,
    /// Grid points per context dimension.
    pub grid: usize,
    /// Half-width of the evaluation grid.
    pub range: f64,
    /// Laps (episodes) per context.
    pub laps: usize,
    /// Seed of the evaluation episodes.
    pub seed: u64,
    /// Checkpoint directory evaluated, or the baseline's name.
    pub source: String,
    /// Which checkpoint of the run: `best`, `latest` or `step-N` (`given` for a checkpoint
    /// directory, `-` for a baseline); evaluations written before it was recorded used the
    /// newest.
    #[serde(default = "newest_checkpoint")]
    pub checkpoint: String,
    /// How a trained agent acted: `sample` (the paper's) or `mode` (what evaluations written
    /// before it was recorded did).
    #[serde(default = "mode_of_policy")]
    pub act: crate::driver::ActMode,
    /// The race scenario's preset.
    #[serde(default)]
    pub preset: ctxrace_common::RacePreset,
    /// Indices (in the grid's `c_v`-major order) of the contexts raced; none: the whole grid.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contexts: Option<Vec<usize>>,
}

fn newest_checkpoint() -> String {
    "latest".into()
}

fn mode_of_policy() -> crate::driver::ActMode {
    crate::driver::ActMode::Mode
}

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

/// Reads every row of a CSV file with a header.
pub fn read_csv<T: DeserializeOwned>(path: &Path) -> Result<Vec<T>> {
    let mut reader =
        csv::Reader::from_path(path).with_context(|| format!("opening {}", path.display()))?;
    reader
        .deserialize()
        .enumerate()
        .map(|(i, row)| row.with_context(|| format!("{} row {}", path.display(), i + 2)))
        .collect()
}

/// Writes rows as a CSV file with a header, replacing the file atomically
/// ([`write_atomic`]: never through a link planted at its path or its temporary's).
pub fn write_csv<T: Serialize>(path: &Path, rows: &[T]) -> Result<()> {
    let mut writer = csv::Writer::from_writer(Vec::new());
    for row in rows {
        writer.serialize(row)?;
    }
    let bytes = writer
        .into_inner()
        .map_err(|e| anyhow::anyhow!("{}", e.error()))
        .with_context(|| format!("writing {}", path.display()))?;
    write_atomic(path, &bytes).with_context(|| format!("writing {}", path.display()))
}

/// Reads a JSON file.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// Writes a value as pretty JSON.
pub fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    // through a temporary file, so that a reader never sees half of it
    write_atomic(path, (text + "\n").as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// The workers' part files of `out` whose names start with `prefix` and end in `.csv`, sorted
/// (result rows `episodes.part-*`, masks `masks.part-*`).
pub fn part_files(out: &Path, prefix: &str) -> Result<Vec<PathBuf>> {
    let mut parts: Vec<PathBuf> = std::fs::read_dir(out)
        .with_context(|| format!("listing {}", out.display()))?
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
    use ctxrace_actor::protocol::EvalEpisode;
    use ctxrace_actor::EpisodeMetrics;
    use ctxrace_common::Context;

    #[test]
    fn csv_round_trip_keeps_missing_lap_times() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("e.csv");
        let lap = |speed, steer, lap_time| {
            let metrics = EpisodeMetrics {
                progress: 0.4,
                lap_time,
                ..EpisodeMetrics::default()
            };
            EvalEpisode::new(Context { speed, steer }, 0, 7, &metrics, lap_time.is_some())
        };
        let rows = vec![lap(0.0, 0.1, Some(31.5)), lap(-0.3, 0.3, None)];
        write_csv(&path, &rows).unwrap();
        assert_eq!(read_csv::<EvalEpisode>(&path).unwrap(), rows);
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
