//! The single-process trainer's resume point, `<run>/resume/`: what [`crate::inline`] holds at
//! an episode boundary, so that a run stopped at any moment (`kill -9` included) and continued
//! with `ctxrace train --inline --resume` writes the same `episodes.csv` and the same
//! checkpoints as the run that was never stopped.
//!
//! ```text
//! resume/                  sealed as a checkpoint is (written whole or not at all)
//!   <the algorithm's files>  weights, optimiser moments, counters (Algorithm::save)
//!   acting.safetensors       the acting policy's weights (they lag the learner's by up to
//!                            policy_every gradient steps)
//!   replay.snapshot          the sample store
//!   returns.toml             the smoothed return behind the best checkpoint
//!   inline.toml              the loop's counters, the positions of its random streams and
//!                            the lengths of the logs it had written
//! ```
//!
//! At an episode boundary nothing else carries over: the next episode's race starts from its
//! seed, the Dreamer agents' recurrent state from zero, and the algorithms draw their noise from
//! `(seed, gradient step)`. Continuing, the trainer cuts the logs back to the recorded lengths
//! and removes the checkpoints written after the point; the rest it computes again, in the same
//! order and so to the same bits. The wall-clock columns (`seconds` and the rates of
//! `metrics.*`, the TensorBoard event files) are the only records that differ.

use crate::best::ReturnTracker;
use crate::checkpoint::{
    checkpoint_step, checkpoints, io_error, verify, write_atomically, write_toml, CheckpointError,
    TRACKER_FILE,
};
use crate::Algorithm;
use ctxrace_nn::policy::CarriedState;
use ctxrace_run::experience::{SampleStore, SourcePosition};
use ctxrace_run::run_dir::{
    METRICS_CSV, METRICS_JSONL, RESUME_DIR, TRAINING_EPISODES, TRAINING_MASKS,
};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The loop's own file in a resume point.
const LOOP_FILE: &str = "inline.toml";
/// The acting policy's weights in a resume point.
const ACTING_FILE: &str = "acting.safetensors";
/// The sample store in a resume point.
const STORE_FILE: &str = "replay.snapshot";
/// The logs a resumed run cuts back to their length at the point.
const LOGS: [&str; 4] = [
    TRAINING_EPISODES,
    TRAINING_MASKS,
    METRICS_JSONL,
    METRICS_CSV,
];

/// The loop's state at an episode boundary, besides the algorithm, the store and the tracker.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopState {
    /// Where the experience source stands.
    pub source: SourcePosition,
    /// Words the batch sampler's random stream has given.
    pub sampler_rng_words: u128,
    /// What the acting policy carries into the next episode.
    pub policy: CarriedState,
    /// Whether the policy is due a reload at the next boundary.
    pub stale_policy: bool,
    /// The decision after which training started, once it has.
    pub trained_after: Option<u64>,
    /// The progress of the last episodes (the progress line's mean).
    pub recent: Vec<f64>,
}

/// [`LoopState`] as `inline.toml` holds it: TOML has no 128-bit integers, so the streams'
/// positions are decimal strings; floats print and parse back to the same bits.
#[derive(Serialize, Deserialize)]
struct LoopFile {
    decisions: u64,
    episodes: u64,
    source_rng_words: String,
    sampler_rng_words: String,
    policy_rng_words: String,
    policy_frames: Vec<Vec<f32>>,
    stale_policy: bool,
    trained_after: Option<u64>,
    recent: Vec<f64>,
    /// Each log's length in bytes when the point was taken.
    logs: BTreeMap<String, u64>,
}

/// A resume point read back: what [`restore`] applies.
pub struct ResumePoint {
    dir: PathBuf,
    /// The loop's state.
    pub state: LoopState,
    /// The smoothed return behind the best checkpoint.
    pub tracker: ReturnTracker,
    /// The acting policy's weights.
    pub acting_weights: Vec<u8>,
    logs: BTreeMap<String, u64>,
}

/// The resume point of the run in `run_dir`, if it has one: `Ok(None)` without, an error naming
/// the file where it is damaged.
pub fn find(run_dir: &Path) -> Result<Option<ResumePoint>, CheckpointError> {
    let dir = run_dir.join(RESUME_DIR);
    if !dir.exists() {
        return Ok(None);
    }
    verify(&dir)?;
    let path = dir.join(LOOP_FILE);
    let text = std::fs::read_to_string(&path).map_err(|e| io_error("reading", &path, e))?;
    let file: LoopFile = toml::from_str(&text).map_err(|e| io_error("parsing", &path, e))?;
    let words = |what: &str, text: &str| {
        text.parse::<u128>()
            .map_err(|e| io_error("parsing", &path, format!("{what} '{text}': {e}")))
    };
    let state = LoopState {
        source: SourcePosition {
            decisions: file.decisions,
            episodes: file.episodes,
            rng_words: words("source_rng_words", &file.source_rng_words)?,
        },
        sampler_rng_words: words("sampler_rng_words", &file.sampler_rng_words)?,
        policy: CarriedState {
            rng_words: words("policy_rng_words", &file.policy_rng_words)?,
            frames: file.policy_frames,
        },
        stale_policy: file.stale_policy,
        trained_after: file.trained_after,
        recent: file.recent,
    };
    let acting = dir.join(ACTING_FILE);
    let acting_weights = std::fs::read(&acting).map_err(|e| io_error("reading", &acting, e))?;
    Ok(Some(ResumePoint {
        tracker: ReturnTracker::load(&dir)?,
        dir,
        state,
        acting_weights,
        logs: file.logs,
    }))
}

impl ResumePoint {
    /// Puts the run folder and `algo` and `store` back where the point was taken: the logs cut
    /// back to their recorded lengths, the checkpoints of later gradient steps removed, the
    /// algorithm's weights, moments and counters and the store's contents restored.
    pub fn restore(
        &self,
        run_dir: &Path,
        algo: &mut dyn Algorithm,
        store: &mut dyn SampleStore,
    ) -> Result<(), CheckpointError> {
        algo.load(&self.dir)?;
        let snapshot = self.dir.join(STORE_FILE);
        store
            .restore(&snapshot)
            .map_err(|e| io_error("restoring", &snapshot, e))?;
        for name in LOGS {
            let path = run_dir.join(name);
            let len = self.logs.get(name).copied().unwrap_or(0);
            cut_back(&path, len)?;
        }
        for later in checkpoints(run_dir)
            .into_iter()
            .filter(|c| checkpoint_step(c).is_some_and(|n| n > algo.steps()))
        {
            std::fs::remove_dir_all(&later).map_err(|e| io_error("removing", &later, e))?;
        }
        Ok(())
    }
}

/// Cuts the log at `path` back to `len` bytes (removes it at 0); a log shorter than `len` was
/// damaged after the point was taken.
fn cut_back(path: &Path, len: u64) -> Result<(), CheckpointError> {
    let found = match std::fs::metadata(path) {
        Ok(m) => m.len(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => 0,
        Err(e) => return Err(io_error("reading", path, e)),
    };
    if found < len {
        return Err(io_error(
            "resuming with",
            path,
            format!(
                "{found} bytes, shorter than the {len} it had at the resume point: the log was \
                 cut since; start the run over (train without --resume)"
            ),
        ));
    }
    if len == 0 {
        return match std::fs::remove_file(path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                Err(io_error("removing", path, e))
            }
            _ => Ok(()),
        };
    }
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(path)
        .map_err(|e| io_error("opening", path, e))?;
    file.set_len(len)
        .and_then(|()| file.sync_all())
        .map_err(|e| io_error("cutting back", path, e))
}

/// Writes the resume point of the run in `run_dir` (replacing the last one, atomically):
/// `state` with `algo`, the acting policy's `acting_weights`, `store` and `tracker`.
pub fn write(
    run_dir: &Path,
    state: &LoopState,
    algo: &dyn Algorithm,
    acting_weights: &[u8],
    store: &dyn SampleStore,
    tracker: &ReturnTracker,
) -> Result<(), CheckpointError> {
    let mut logs = BTreeMap::new();
    for name in LOGS {
        let path = run_dir.join(name);
        let len = match std::fs::metadata(&path) {
            Ok(m) => m.len(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => 0,
            Err(e) => return Err(io_error("reading", &path, e)),
        };
        logs.insert(name.to_string(), len);
    }
    let file = LoopFile {
        decisions: state.source.decisions,
        episodes: state.source.episodes,
        source_rng_words: state.source.rng_words.to_string(),
        sampler_rng_words: state.sampler_rng_words.to_string(),
        policy_rng_words: state.policy.rng_words.to_string(),
        policy_frames: state.policy.frames.clone(),
        stale_policy: state.stale_policy,
        trained_after: state.trained_after,
        recent: state.recent.clone(),
        logs,
    };
    write_atomically(&run_dir.join(RESUME_DIR), |tmp| {
        algo.save(tmp)?;
        let acting = tmp.join(ACTING_FILE);
        std::fs::write(&acting, acting_weights).map_err(|e| io_error("writing", &acting, e))?;
        let snapshot = tmp.join(STORE_FILE);
        store
            .save(&snapshot)
            .map_err(|e| io_error("writing", &snapshot, e))?;
        write_toml(&tmp.join(TRACKER_FILE), tracker)?;
        write_toml(&tmp.join(LOOP_FILE), &file)
    })?;
    Ok(())
}

/// Removes the run's resume point (a finished run needs none).
pub fn remove(run_dir: &Path) -> Result<(), CheckpointError> {
    let dir = run_dir.join(RESUME_DIR);
    match std::fs::remove_dir_all(&dir) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io_error("removing", &dir, e)),
        _ => Ok(()),
    }
}
