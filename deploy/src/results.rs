//! Evaluation and training results on disk: what `ctxrace eval` and the trainers write and what
//! `ctxrace report` reads.
//!
//! An evaluation directory (`<run>/eval/` by default) holds:
//! - `meta.json`: [`EvalMeta`], which agent on which track against how many rivals;
//! - `episodes.csv`: one [`EpisodeRecord`] per evaluation episode (lap);
//! - `contexts.csv` and `contexts.json`: one [`ContextSummary`] per context of the grid.
//!
//! A training run directory holds `episodes.csv` with one [`TrainingEpisode`] per finished
//! training episode (the training curves).
//!
//! **Definitions.** PG: the largest fraction of the lap the ego completed in the episode.
//! OT: +1 each time the ego passes a rival, −1 each time a rival passes it, by track progress,
//! summed over the episode. A2A: the episode ended in an ego–rival collision; per context it is
//! reported as the number of such episodes per 50 laps, as the paper does. A context is
//! in-distribution when both of its values lie inside the training range `[−r, r]`.

use anyhow::{Context as _, Result};
use serde::{de::DeserializeOwned, Deserialize, Serialize};
use std::path::Path;

/// Laps per context that A2A counts are scaled to (the paper's protocol).
pub const A2A_PER_LAPS: f64 = 50.0;

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
}

fn newest_checkpoint() -> String {
    "latest".into()
}

fn mode_of_policy() -> crate::driver::ActMode {
    crate::driver::ActMode::Mode
}

/// One evaluation episode.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// Index of the lap within its context, `0..laps`.
    pub lap: usize,
    /// Seed the episode was reset with.
    pub seed: u64,
    /// PG of the episode, `[0, 1]`.
    pub progress: f64,
    /// OT of the episode.
    pub overtakes: i32,
    /// The episode ended in an ego–rival collision.
    pub a2a: bool,
    /// The episode ended with the ego hitting a wall.
    pub wall_crash: bool,
    /// The ego completed the lap.
    pub lap_complete: bool,
    /// Lap time when completed (s), else empty.
    pub lap_time: Option<f64>,
    /// Decisions taken.
    pub steps: usize,
    /// Sum of rewards.
    pub episode_return: f64,
}

/// The episodes of one context, aggregated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ContextSummary {
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// Both context values inside the training range.
    pub in_distribution: bool,
    /// Episodes aggregated.
    pub laps: usize,
    /// Mean PG.
    pub progress: f64,
    /// Mean OT per episode.
    pub overtakes: f64,
    /// Episodes ending in an ego–rival collision, per [`A2A_PER_LAPS`] laps.
    pub a2a: f64,
    /// Fraction of episodes ending at a wall.
    pub wall_crash: f64,
    /// Fraction of episodes completing the lap.
    pub lap_complete: f64,
    /// Mean episode return.
    pub episode_return: f64,
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

/// Both context values lie in `[−range, range]` (with a tolerance for grid rounding).
pub fn in_distribution(context_speed: f64, context_steer: f64, range: f64) -> bool {
    let inside = |c: f64| c.abs() <= range + 1e-9;
    inside(context_speed) && inside(context_steer)
}

/// Aggregates episodes per context, in the order contexts first appear.
pub fn summarise(episodes: &[EpisodeRecord], train_range: f64) -> Vec<ContextSummary> {
    let mut keys: Vec<(f64, f64)> = Vec::new();
    for e in episodes {
        let key = (e.context_speed, e.context_steer);
        if !keys.contains(&key) {
            keys.push(key);
        }
    }
    keys.into_iter()
        .map(|(cv, ct)| {
            let eps: Vec<&EpisodeRecord> = episodes
                .iter()
                .filter(|e| e.context_speed == cv && e.context_steer == ct)
                .collect();
            let n = eps.len() as f64;
            let mean =
                |f: &dyn Fn(&EpisodeRecord) -> f64| eps.iter().map(|e| f(e)).sum::<f64>() / n;
            ContextSummary {
                context_speed: cv,
                context_steer: ct,
                in_distribution: in_distribution(cv, ct, train_range),
                laps: eps.len(),
                progress: mean(&|e| e.progress),
                overtakes: mean(&|e| e.overtakes as f64),
                a2a: mean(&|e| e.a2a as u8 as f64) * A2A_PER_LAPS,
                wall_crash: mean(&|e| e.wall_crash as u8 as f64),
                lap_complete: mean(&|e| e.lap_complete as u8 as f64),
                episode_return: mean(&|e| e.episode_return),
            }
        })
        .collect()
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

/// Writes rows as a CSV file with a header (replacing the file).
pub fn write_csv<T: Serialize>(path: &Path, rows: &[T]) -> Result<()> {
    let mut writer =
        csv::Writer::from_path(path).with_context(|| format!("creating {}", path.display()))?;
    for row in rows {
        writer.serialize(row)?;
    }
    writer
        .flush()
        .with_context(|| format!("writing {}", path.display()))
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
    let mut tmp = path.as_os_str().to_os_string();
    tmp.push(".tmp");
    std::fs::write(&tmp, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(cv: f64, ct: f64, progress: f64, a2a: bool) -> EpisodeRecord {
        EpisodeRecord {
            context_speed: cv,
            context_steer: ct,
            lap: 0,
            seed: 0,
            progress,
            overtakes: 1,
            a2a,
            wall_crash: false,
            lap_complete: progress >= 1.0,
            lap_time: None,
            steps: 10,
            episode_return: 2.0,
        }
    }

    #[test]
    fn summary_per_context_with_a2a_per_fifty_laps() {
        let eps = [
            episode(0.1, 0.0, 1.0, false),
            episode(0.1, 0.0, 0.5, true),
            episode(0.3, -0.2, 0.2, true),
        ];
        let s = summarise(&eps, 0.15);
        assert_eq!(s.len(), 2);
        assert!(s[0].in_distribution && !s[1].in_distribution);
        assert!((s[0].progress - 0.75).abs() < 1e-12);
        assert!((s[0].a2a - 25.0).abs() < 1e-12);
        assert!((s[0].lap_complete - 0.5).abs() < 1e-12);
        assert!((s[1].a2a - 50.0).abs() < 1e-12);
    }

    #[test]
    fn csv_round_trip_keeps_missing_lap_times() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("e.csv");
        let mut a = episode(0.0, 0.1, 1.0, false);
        a.lap_time = Some(31.5);
        let rows = vec![a, episode(-0.3, 0.3, 0.4, true)];
        write_csv(&path, &rows).unwrap();
        assert_eq!(read_csv::<EpisodeRecord>(&path).unwrap(), rows);
    }
}
