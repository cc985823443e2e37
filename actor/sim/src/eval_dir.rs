//! An evaluation folder: the protocol's defaults, which contexts it races, and its output
//! layout. The coordinator writes `meta.json` ([`prepare`]); each worker appends its finished
//! episodes to `episodes.part-K.csv` ([`part_path`], [`append_csv`]) and cMask's masks to
//! `masks.part-K.csv`, so an interrupted evaluation resumes where it stopped ([`finished`]: a
//! rerun skips every (context, lap) already on disk); [`merge`] then writes `episodes.csv`, the
//! per-context summaries (`contexts.csv`, `contexts.json`) and `masks.csv.gz`.

use crate::evaluation::{summarise, ContextSummary, EvalEpisode, EvalMeta};
use crate::masks::{self, MaskFileError};
use ctxrace_config::Context;
use ctxrace_run::path_error::PathIoError;
use ctxrace_run::results::{self, ResultsError};
use ctxrace_run::run_dir::{
    open_append, read_regular, write_atomic, EVAL_CONTEXTS_CSV, EVAL_CONTEXTS_JSON, EVAL_EPISODES,
    EVAL_META,
};
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// Grid points per context dimension (the paper's 7 × 7).
pub const GRID: usize = 7;
/// Half-width of the context grid (the paper's ±0.3).
pub const RANGE: f64 = 0.3;
/// Episodes (laps) per context (the paper's 50).
pub const LAPS: usize = 50;
/// Half-width of the training contexts, where a run does not say (the paper's ±0.15).
pub const TRAIN_RANGE: f64 = 0.15;
/// The track a reference policy is evaluated on when none is named.
pub const REFERENCE_TRACK: &str = "f1_esp";
/// The rivals a reference policy races when their number is not given.
pub const REFERENCE_RIVALS: usize = 3;

/// Prefix of a worker's episode file (`episodes.part-K.csv`).
const PART_PREFIX: &str = "episodes.part-";

/// Why an evaluation folder could not be prepared, resumed or merged.
#[derive(Debug, thiserror::Error)]
pub enum EvalDirError {
    /// A file could not be created, read, written or removed.
    #[error(transparent)]
    Io(#[from] PathIoError),
    /// A part file could not be opened or written as CSV.
    #[error("{}", .path.display())]
    Csv {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: csv::Error,
    },
    /// A record could not be read or written.
    #[error(transparent)]
    Results(#[from] ResultsError),
    /// cMask's mask records could not be merged.
    #[error(transparent)]
    Masks(#[from] MaskFileError),
    /// The folder holds the results of another evaluation.
    #[error(
        "{} holds results of another evaluation ({} on {}, {} rivals, grid {}, range {}, {} laps, \
         seed {}); pass --fresh to replace them or --out for another directory",
        .dir.display(), .old.algo, .old.track, .old.rivals, .old.grid, .old.range, .old.laps,
        .old.seed
    )]
    OtherEvaluation {
        /// The folder.
        dir: PathBuf,
        /// The evaluation it holds.
        old: Box<EvalMeta>,
    },
    /// A part file holds an episode this evaluation does not race.
    #[error(
        "{} holds an episode outside this evaluation (context {speed}, {steer}, lap {lap}); \
         pass --fresh",
        .part.display()
    )]
    Outside {
        /// The part file.
        part: PathBuf,
        /// The episode's `c_v`.
        speed: f64,
        /// The episode's `c_θ`.
        steer: f64,
        /// Its lap.
        lap: usize,
    },
    /// Not every episode is on disk yet.
    #[error("{} holds {have} of {expected} episodes; rerun the same command to finish", .dir.display())]
    Incomplete {
        /// The folder.
        dir: PathBuf,
        /// Episodes on disk.
        have: usize,
        /// Episodes the evaluation races.
        expected: usize,
    },
}

/// `Result` of an evaluation folder's operations.
pub type Result<T> = std::result::Result<T, EvalDirError>;

/// A `--contexts` selection that names no context of the grid.
#[derive(Debug, thiserror::Error)]
#[error(
    "--contexts {spec:?}: {why}; give indices 0 to {last} of the grid (c_v major), ranges such \
     as 17-48, or skip-first:K"
)]
pub struct ContextsError {
    /// The selection as given.
    pub spec: String,
    /// What is wrong with it.
    pub why: String,
    /// The grid's last index.
    pub last: usize,
}

/// Parses a selection of the contexts of a grid of `n`: `skip-first:K`, or a comma-separated
/// list of indices and inclusive ranges `a-b` (indices in the grid's `c_v`-major order, the
/// paper's code's). Returns the sorted, distinct indices.
pub fn parse_contexts(spec: &str, n: usize) -> std::result::Result<Vec<usize>, ContextsError> {
    let bad = |why: String| ContextsError {
        spec: spec.to_string(),
        why,
        last: n.saturating_sub(1),
    };
    let index = |t: &str| -> std::result::Result<usize, ContextsError> {
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

impl EvalMeta {
    /// The contexts of its grid (all of them, raced or not: indices stay the grid's).
    pub fn grid_contexts(&self) -> Vec<Context> {
        Context::grid(self.grid, self.range)
    }

    /// The grid indices it races.
    pub fn raced(&self) -> Vec<usize> {
        match &self.contexts {
            Some(chosen) => chosen.clone(),
            None => (0..self.grid * self.grid).collect(),
        }
    }
}

/// The default folder of a reference policy's evaluation: `eval-<policy>-<track>-<rivals>r`.
pub fn reference_dir(policy: &str, track: &str, rivals: usize) -> PathBuf {
    PathBuf::from(format!(
        "eval-{policy}-{}-{rivals}r",
        track.replace([':', '/'], "_")
    ))
}

/// Creates `out`, checks that earlier results belong to the same evaluation (or removes them
/// with `fresh`) and writes `meta.json`.
pub fn prepare(out: &Path, meta: &EvalMeta, fresh: bool) -> Result<()> {
    std::fs::create_dir_all(out).map_err(PathIoError::at("creating", out))?;
    let meta_path = out.join(EVAL_META);
    if fresh {
        for entry in std::fs::read_dir(out).map_err(PathIoError::at("listing", out))? {
            let path = entry.map_err(PathIoError::at("listing", out))?.path();
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if ["episodes", "contexts", "masks"]
                .iter()
                .any(|prefix| name.starts_with(prefix))
            {
                std::fs::remove_file(&path).map_err(PathIoError::at("removing", &path))?;
            }
        }
    } else if meta_path.exists() {
        let old: EvalMeta = results::read_json(&meta_path)?;
        if &old != meta {
            return Err(EvalDirError::OtherEvaluation {
                dir: out.to_path_buf(),
                old: Box::new(old),
            });
        }
    }
    Ok(results::write_json(&meta_path, meta)?)
}

/// The episode file of worker `shard` in `out`.
pub fn part_path(out: &Path, shard: usize) -> PathBuf {
    out.join(format!("{PART_PREFIX}{shard:03}.csv"))
}

/// Every finished episode on disk with its context's index in the grid of `meta` (a torn
/// last line of a killed worker is skipped).
pub fn read_parts(out: &Path, meta: &EvalMeta) -> Result<Vec<(usize, EvalEpisode)>> {
    let grid = meta.grid_contexts();
    let chosen = meta.raced();
    let mut rows = Vec::new();
    for part in results::part_files(out, PART_PREFIX)? {
        let mut reader = csv::Reader::from_path(&part).map_err(|source| EvalDirError::Csv {
            path: part.clone(),
            source,
        })?;
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
                _ => {
                    return Err(EvalDirError::Outside {
                        part,
                        speed: e.context_speed,
                        steer: e.context_steer,
                        lap: e.lap,
                    })
                }
            }
        }
    }
    Ok(rows)
}

/// The `(context index, lap)` pairs already on disk.
pub fn finished(out: &Path, meta: &EvalMeta) -> Result<HashSet<(usize, usize)>> {
    Ok(read_parts(out, meta)?
        .into_iter()
        .map(|(c, e)| (c, e.lap))
        .collect())
}

/// The `(context index, lap)` pairs of `meta` not yet on disk in `out`, in order.
pub fn todo(out: &Path, meta: &EvalMeta) -> Result<Vec<(usize, usize)>> {
    let done = finished(out, meta)?;
    Ok(meta
        .raced()
        .into_iter()
        .flat_map(|c| (0..meta.laps).map(move |l| (c, l)))
        .filter(|key| !done.contains(key))
        .collect())
}

/// Cuts a torn last line (a worker killed mid-write) so that appending starts on a fresh line.
fn trim_torn_line(path: &Path) -> Result<()> {
    let bytes = match read_regular(path, u64::MAX) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(PathIoError::at("reading", path)(e).into()),
    };
    if bytes.last().is_some_and(|&b| b != b'\n') {
        let keep = bytes.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
        write_atomic(path, &bytes[..keep]).map_err(PathIoError::at("repairing", path))?;
    }
    Ok(())
}

/// A CSV writer appending to `path` (after cutting a torn last line), with a header when the
/// file is new or empty.
pub fn append_csv(path: &Path) -> Result<csv::Writer<std::fs::File>> {
    trim_torn_line(path)?;
    let fresh = match std::fs::metadata(path) {
        Ok(m) => m.len() == 0,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => true,
        Err(e) => return Err(PathIoError::at("reading", path)(e).into()),
    };
    let file = open_append(path).map_err(PathIoError::at("opening", path))?;
    Ok(csv::WriterBuilder::new()
        .has_headers(fresh)
        .from_writer(file))
}

/// The merged records of a finished evaluation.
#[derive(Clone, Debug)]
pub struct Merged {
    /// One summary per context raced.
    pub summary: Vec<ContextSummary>,
    /// cMask's mask rows merged into `masks.csv.gz`, if the agent has a mask.
    pub mask_rows: Option<usize>,
}

/// Merges the workers' rows of a finished evaluation into `episodes.csv` (one per episode, in
/// context and lap order), writes the per-context summaries (`contexts.csv`, `contexts.json`)
/// and merges cMask's masks; fails if an episode is missing.
pub fn merge(out: &Path, meta: &EvalMeta) -> Result<Merged> {
    let mut rows = read_parts(out, meta)?;
    rows.sort_by_key(|(c, e)| (*c, e.lap));
    rows.dedup_by_key(|(c, e)| (*c, e.lap));
    let chosen = meta.raced();
    let expected = chosen.len() * meta.laps;
    if rows.len() != expected {
        return Err(EvalDirError::Incomplete {
            dir: out.to_path_buf(),
            have: rows.len(),
            expected,
        });
    }
    let episodes: Vec<EvalEpisode> = rows.into_iter().map(|(_, e)| e).collect();
    results::write_csv(&out.join(EVAL_EPISODES), &episodes)?;
    let summary = summarise(&episodes, meta.train_range);
    results::write_csv(&out.join(EVAL_CONTEXTS_CSV), &summary)?;
    results::write_json(&out.join(EVAL_CONTEXTS_JSON), &summary)?;
    let grid = meta.grid_contexts();
    let kept = |c: Context, lap: usize| {
        lap < meta.laps
            && grid
                .iter()
                .position(|&g| g == c)
                .is_some_and(|i| chosen.contains(&i))
    };
    let mask_rows = masks::merge_parts(out, kept)?;
    Ok(Merged { summary, mask_rows })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evaluation::episode_seed;

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
