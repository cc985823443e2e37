//! What cMask's mask learned: every decision's context mask in evaluation, where it was chosen.
//!
//! `ctxrace eval` of a cMask agent writes `masks.csv.gz` beside `episodes.csv`: one
//! [`MaskStep`] per decision (gzip-compressed CSV with a header; `zcat` reads it). The columns
//! are the quantities the paper's code records per test step (its `Lap_N_history_*.npy`: the
//! pose, the lap progress and the two mask values, `plot_masks.py` and `plot_masks_map.py`), so
//! that its records converted by `deploy/paper_parity.sh masks` read the same. Each worker
//! appends an episode's rows to `masks.part-K.csv` before the episode's own row, so a resumed
//! evaluation may hold an episode twice (it is rerun whole, with the same seed and so the same
//! rows): the merge keeps one row per (context, lap, step) and removes the parts.
//!
//! `ctxrace report` reads the file back as a [`MaskSummary`]: the mean of each mask component per
//! context and along the lap.

use crate::driver::Decided;
use crate::race::RaceEnv;
use ctxrace_config::Context;
use ctxrace_run::path_error::PathIoError;
use ctxrace_run::results::ResultsError;
use ctxrace_run::run_dir::write_atomic;
use flate2::read::MultiGzDecoder;
use flate2::write::GzEncoder;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

/// A mask file that could not be read, written or trusted.
#[derive(Debug, thiserror::Error)]
pub enum MaskFileError {
    /// A file could not be opened, written or removed.
    #[error(transparent)]
    Io(#[from] PathIoError),
    /// A row could not be read or written as CSV.
    #[error("{} row {row}", .path.display())]
    Csv {
        /// The file.
        path: PathBuf,
        /// The row's line (the header is line 1).
        row: usize,
        /// The cause.
        #[source]
        source: csv::Error,
    },
    /// A mask outside `[0, 1]` or a value that is not a number.
    #[error(
        "{} row {row}: a mask outside [0, 1] or a value that is not a number (masks \
         {mask_speed}, {mask_steer}); the file is damaged: evaluate again with --fresh",
        .path.display()
    )]
    Damaged {
        /// The file.
        path: PathBuf,
        /// The row's line.
        row: usize,
        /// Its `c_v` mask.
        mask_speed: f64,
        /// Its `c_θ` mask.
        mask_steer: f64,
    },
    /// The file holds no decision.
    #[error("{}: no decisions", .0.display())]
    Empty(PathBuf),
    /// The workers' part files could not be listed.
    #[error(transparent)]
    Parts(#[from] ResultsError),
}

/// `Result` of reading or writing mask files.
pub type Result<T> = std::result::Result<T, MaskFileError>;

/// The merged mask file of an evaluation directory.
pub const MASKS_FILE: &str = "masks.csv.gz";

/// Prefix of a worker's mask file (`masks.part-K.csv`).
const PART_PREFIX: &str = "masks.part-";

/// Bins of lap progress the mean mask along the lap is taken over.
pub const PROGRESS_BINS: usize = 50;

/// One decision of a cMask agent in evaluation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaskStep {
    /// Rival speed context `c_v` of the episode.
    pub context_speed: f64,
    /// Rival steering context `c_θ` of the episode.
    pub context_steer: f64,
    /// Lap (episode) index within its context.
    pub lap: usize,
    /// Decision index within the episode, from 0.
    pub step: usize,
    /// Ego progress along the lap when it decided: centreline distance travelled over the lap
    /// length (negative just behind the start line).
    pub progress: f64,
    /// Ego position x when it decided (m).
    pub x: f64,
    /// Ego position y when it decided (m).
    pub y: f64,
    /// The mask on `c_v`, in `[0, 1]`.
    pub mask_speed: f64,
    /// The mask on `c_θ`, in `[0, 1]`.
    pub mask_steer: f64,
}

/// Rounds to `decimals` places (the file keeps what a figure can show).
fn round(v: f64, decimals: i32) -> f64 {
    let scale = 10f64.powi(decimals);
    (v * scale).round() / scale
}

/// Collects the masks of one episode, each with the pose at which it was chosen.
pub struct MaskRecorder {
    context: Context,
    lap: usize,
    /// Progress, x and y after the previous decision (or the reset).
    pose: (f64, f64, f64),
    rows: Vec<MaskStep>,
}

impl MaskRecorder {
    /// A recorder for lap `lap` of `context`.
    pub fn new(context: Context, lap: usize) -> Self {
        Self {
            context,
            lap,
            pose: (0.0, 0.0, 0.0),
            rows: Vec::new(),
        }
    }

    /// Takes one observation of [`crate::driver::Ego::drive_observed`].
    pub fn observe(&mut self, env: &RaceEnv, decided: &Decided) {
        if let Some([speed, steer]) = decided.mask {
            let (progress, x, y) = self.pose;
            self.rows.push(MaskStep {
                context_speed: self.context.speed,
                context_steer: self.context.steer,
                lap: self.lap,
                step: self.rows.len(),
                progress: round(progress, 4),
                x: round(x, 3),
                y: round(y, 3),
                mask_speed: round(f64::from(speed), 4),
                mask_steer: round(f64::from(steer), 4),
            });
        }
        let ego = &env.cars()[0];
        let at = ego.vehicle.position();
        self.pose = (ego.travelled / env.track().length(), at.x, at.y);
    }

    /// The rows recorded (none for an agent without a mask).
    pub fn into_rows(self) -> Vec<MaskStep> {
        self.rows
    }
}

/// The mask file of worker `shard` in `out`.
pub fn part_path(out: &Path, shard: usize) -> PathBuf {
    out.join(format!("{PART_PREFIX}{shard:03}.csv"))
}

/// The workers' mask files in `out`.
fn part_files(out: &Path) -> Result<Vec<PathBuf>> {
    Ok(ctxrace_run::results::part_files(out, PART_PREFIX)?)
}

/// Merges the workers' mask files of `out` into [`MASKS_FILE`], keeping the rows of the
/// contexts and laps `keep` accepts (one per decision, in context, lap and step order), and
/// removes the parts. Without parts (not a cMask agent, or merged before) nothing changes.
/// Returns the rows merged.
pub fn merge_parts(out: &Path, keep: impl Fn(Context, usize) -> bool) -> Result<Option<usize>> {
    let parts = part_files(out)?;
    if parts.is_empty() {
        return Ok(None);
    }
    let mut rows: Vec<MaskStep> = Vec::new();
    for part in &parts {
        let mut reader = csv::Reader::from_path(part).map_err(|source| MaskFileError::Csv {
            path: part.clone(),
            row: 1,
            source,
        })?;
        for row in reader.deserialize::<MaskStep>() {
            match row {
                Ok(r) => {
                    let context = Context {
                        speed: r.context_speed,
                        steer: r.context_steer,
                    };
                    if keep(context, r.lap) {
                        rows.push(r);
                    }
                }
                // a worker killed mid-write: the episode was raced again
                Err(err) => tracing::warn!("skipping a torn row of {}: {err}", part.display()),
            }
        }
    }
    let key = |r: &MaskStep| (r.context_speed, r.context_steer, r.lap, r.step);
    rows.sort_by(|a, b| {
        let (ka, kb) = (key(a), key(b));
        ka.0.total_cmp(&kb.0)
            .then(ka.1.total_cmp(&kb.1))
            .then(ka.2.cmp(&kb.2))
            .then(ka.3.cmp(&kb.3))
    });
    rows.dedup_by(|a, b| key(a) == key(b));
    write_masks(&out.join(MASKS_FILE), &rows)?;
    for part in parts {
        std::fs::remove_file(&part).map_err(PathIoError::at("removing", &part))?;
    }
    Ok(Some(rows.len()))
}

/// Writes `rows` as a gzip-compressed CSV file with a header.
pub fn write_masks(path: &Path, rows: &[MaskStep]) -> Result<()> {
    let gz = GzEncoder::new(Vec::new(), flate2::Compression::default());
    let mut writer = csv::Writer::from_writer(gz);
    for (i, row) in rows.iter().enumerate() {
        writer.serialize(row).map_err(|source| MaskFileError::Csv {
            path: path.to_path_buf(),
            row: i + 2,
            source,
        })?;
    }
    let mut gz = writer
        .into_inner()
        .map_err(|e| PathIoError::at("writing", path)(e.into_error()))?;
    gz.flush().map_err(PathIoError::at("writing", path))?;
    let bytes = gz.finish().map_err(PathIoError::at("writing", path))?;
    Ok(write_atomic(path, &bytes).map_err(PathIoError::at("writing", path))?)
}

/// Mean masks of one context.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ContextMasks {
    /// Rival speed context `c_v`.
    pub context_speed: f64,
    /// Rival steering context `c_θ`.
    pub context_steer: f64,
    /// Sums of the `c_v` and `c_θ` masks over the decisions.
    pub sum: [f64; 2],
    /// Decisions.
    pub count: usize,
    /// Sums of both masks and decisions per bin of lap progress (of [`PROGRESS_BINS`] over
    /// `[0, 1]`, progress clamped into it).
    pub along: Vec<([f64; 2], usize)>,
    /// The decisions of its longest lap (the first of equals): position and both masks.
    pub longest_lap: Vec<LapPoint>,
}

/// One decision of a lap drawn on the track: position x, y (m) and both masks.
pub type LapPoint = (f64, f64, [f64; 2]);

impl ContextMasks {
    /// The context.
    pub fn context(&self) -> Context {
        Context {
            speed: self.context_speed,
            steer: self.context_steer,
        }
    }

    /// Mean of mask component `k` (0: `c_v`, 1: `c_θ`) over the decisions.
    pub fn mean(&self, k: usize) -> f64 {
        self.sum[k] / self.count.max(1) as f64
    }
}

/// An evaluation's masks, summarised per context (in the order contexts first appear).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MaskSummary {
    /// One entry per context.
    pub contexts: Vec<ContextMasks>,
    /// Decisions read.
    pub decisions: usize,
    /// The smallest and largest mask value read, per component.
    pub range: [(f64, f64); 2],
}

/// The progress bin of `progress`.
pub fn progress_bin(progress: f64) -> usize {
    ((progress.clamp(0.0, 1.0) * PROGRESS_BINS as f64) as usize).min(PROGRESS_BINS - 1)
}

/// Reads an evaluation directory's [`MASKS_FILE`], if it has one, checking every mask value
/// lies in `[0, 1]` and every number is finite.
pub fn load_summary(dir: &Path) -> Result<Option<MaskSummary>> {
    let path = dir.join(MASKS_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    let file = std::fs::File::open(&path).map_err(PathIoError::at("opening", &path))?;
    let mut reader = csv::Reader::from_reader(MultiGzDecoder::new(std::io::BufReader::new(file)));
    let mut summary = MaskSummary {
        range: [(f64::INFINITY, f64::NEG_INFINITY); 2],
        ..MaskSummary::default()
    };
    // the lap being read (rows come lap by lap): its context, lap index and points
    let mut lap: Option<(Context, usize, Vec<LapPoint>)> = None;
    for (i, row) in reader.deserialize::<MaskStep>().enumerate() {
        let r = row.map_err(|source| MaskFileError::Csv {
            path: path.clone(),
            row: i + 2,
            source,
        })?;
        let masks = [r.mask_speed, r.mask_steer];
        let numbers = [r.context_speed, r.context_steer, r.progress, r.x, r.y];
        if !numbers.iter().all(|v| v.is_finite()) || !masks.iter().all(|m| (0.0..=1.0).contains(m))
        {
            return Err(MaskFileError::Damaged {
                path,
                row: i + 2,
                mask_speed: r.mask_speed,
                mask_steer: r.mask_steer,
            });
        }
        let context = Context {
            speed: r.context_speed,
            steer: r.context_steer,
        };
        if lap.as_ref().is_some_and(|l| (l.0, l.1) != (context, r.lap)) {
            keep_if_longest(&mut summary, lap.take());
        }
        lap.get_or_insert_with(|| (context, r.lap, Vec::new()))
            .2
            .push((r.x, r.y, masks));
        let index = match summary.contexts.iter().position(|c| c.context() == context) {
            Some(i) => i,
            None => {
                summary.contexts.push(ContextMasks {
                    context_speed: r.context_speed,
                    context_steer: r.context_steer,
                    along: vec![([0.0; 2], 0); PROGRESS_BINS],
                    ..ContextMasks::default()
                });
                summary.contexts.len() - 1
            }
        };
        let cell = &mut summary.contexts[index];
        let bin = &mut cell.along[progress_bin(r.progress)];
        for (k, m) in masks.into_iter().enumerate() {
            cell.sum[k] += m;
            bin.0[k] += m;
            let (lo, hi) = &mut summary.range[k];
            (*lo, *hi) = (lo.min(m), hi.max(m));
        }
        cell.count += 1;
        bin.1 += 1;
        summary.decisions += 1;
    }
    keep_if_longest(&mut summary, lap);
    if summary.decisions == 0 {
        return Err(MaskFileError::Empty(path));
    }
    Ok(Some(summary))
}

/// Makes a finished `lap` its context's longest lap if it has more decisions.
fn keep_if_longest(summary: &mut MaskSummary, lap: Option<(Context, usize, Vec<LapPoint>)>) {
    let Some((context, _, points)) = lap else {
        return;
    };
    if let Some(c) = summary.contexts.iter_mut().find(|c| c.context() == context) {
        if points.len() > c.longest_lap.len() {
            c.longest_lap = points;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(cv: f64, lap: usize, step: usize, progress: f64, m: [f64; 2]) -> MaskStep {
        MaskStep {
            context_speed: cv,
            context_steer: 0.0,
            lap,
            step,
            progress,
            x: 1.0,
            y: 2.0,
            mask_speed: m[0],
            mask_steer: m[1],
        }
    }

    fn write_part(path: &Path, rows: &[MaskStep], torn: &str) {
        let mut w = csv::Writer::from_path(path).unwrap();
        for r in rows {
            w.serialize(r).unwrap();
        }
        w.flush().unwrap();
        drop(w);
        let mut f = std::fs::OpenOptions::new().append(true).open(path).unwrap();
        f.write_all(torn.as_bytes()).unwrap();
    }

    #[test]
    fn parts_merge_once_per_decision_and_the_summary_means_them() {
        let dir = tempfile::tempdir().unwrap();
        // worker 0 raced lap 0 of c_v = 0.3 twice (killed before its episode row) and was
        // killed mid-row; worker 1 raced c_v = -0.3, and a lap the evaluation does not keep
        let a = [
            step(0.3, 0, 0, 0.0, [1.0, 0.0]),
            step(0.3, 0, 1, 0.5, [0.5, 0.25]),
        ];
        write_part(
            &part_path(dir.path(), 0),
            &[a.clone(), a.clone()].concat(),
            "0.3,0.0,1,0,0.",
        );
        write_part(
            &part_path(dir.path(), 1),
            &[
                step(-0.3, 0, 0, 0.99, [0.0, 1.0]),
                step(-0.3, 7, 0, 0.2, [0.0, 1.0]),
            ],
            "",
        );
        let rows = merge_parts(dir.path(), |_, lap| lap < 5).unwrap();
        assert_eq!(rows, Some(3));
        assert!(part_files(dir.path()).unwrap().is_empty());
        // merged before: nothing to do, the file stays
        assert_eq!(merge_parts(dir.path(), |_, _| true).unwrap(), None);

        let s = load_summary(dir.path()).unwrap().unwrap();
        assert_eq!(s.decisions, 3);
        assert_eq!(s.range, [(0.0, 1.0), (0.0, 1.0)]);
        let cell = |cv: f64| s.contexts.iter().find(|c| c.context_speed == cv).unwrap();
        assert_eq!((cell(0.3).mean(0), cell(0.3).mean(1)), (0.75, 0.125));
        assert_eq!((cell(-0.3).count, cell(-0.3).mean(1)), (1, 1.0));
        assert_eq!(cell(0.3).along[progress_bin(0.5)], ([0.5, 0.25], 1));
        assert_eq!(cell(-0.3).along[PROGRESS_BINS - 1], ([0.0, 1.0], 1));
        assert_eq!(
            cell(0.3).longest_lap,
            [(1.0, 2.0, [1.0, 0.0]), (1.0, 2.0, [0.5, 0.25])]
        );
    }

    #[test]
    fn a_mask_outside_its_range_is_named_with_its_row() {
        let dir = tempfile::tempdir().unwrap();
        let rows = [
            step(0.0, 0, 0, 0.1, [0.5, 0.5]),
            step(0.0, 0, 1, 0.2, [1.5, 0.5]),
        ];
        write_masks(&dir.path().join(MASKS_FILE), &rows).unwrap();
        let err = format!("{:#}", load_summary(dir.path()).unwrap_err());
        assert!(err.contains("row 3") && err.contains("1.5"), "{err}");
        assert_eq!(load_summary(&dir.path().join("none")).unwrap(), None);
    }
}
