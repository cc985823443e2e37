//! The run's `best` checkpoint, kept as the paper's code kept it (Utils/HistoryStructs.py): the
//! training-episode returns `R_k` are smoothed exponentially,
//!
//! ```text
//! ē_1 = R_1,   ē_k = (1 − α) ē_{k−1} + α R_k,   α = 0.2,
//! ```
//!
//! and whenever `ē_k` exceeds every earlier value the acting policy is saved as
//! `<run>/checkpoints/best/` (its weights, `agent.toml` and [`BEST_FILE`]); `ctxrace eval`
//! evaluates it by default, as the paper did. Only episodes the policy drove from start to end
//! count, not those of the random prefill. The smoother's state is saved with every regular
//! checkpoint, so a restarted learner carries on with it.

use crate::checkpoint::{
    io_error, write_atomically, write_policy_files, write_toml, Result, MANIFEST_FILE, TRACKER_FILE,
};
use crate::Algorithm;
use ctxrace_run::checkpoint::{best_at_dir, best_checkpoint, BEST_FILE};
use ctxrace_run::run_dir::{BEST_DIR, CHECKPOINTS};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Weight of the newest return in the smoothed return (the paper code's `ewma` default).
pub const SMOOTHING: f64 = 0.2;

/// The exponentially smoothed training return and its peak so far.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReturnTracker {
    /// Episodes observed.
    pub episodes: u64,
    /// `ē_k` after the last episode.
    pub smoothed: f64,
    /// The largest `ē_k` so far.
    pub peak: Option<f64>,
}

impl ReturnTracker {
    /// Takes one episode's return; `true` when the smoothed return reached a new peak.
    pub fn observe(&mut self, episode_return: f64) -> bool {
        if !episode_return.is_finite() {
            return false;
        }
        self.smoothed = if self.episodes == 0 {
            episode_return
        } else {
            (1.0 - SMOOTHING) * self.smoothed + SMOOTHING * episode_return
        };
        self.episodes += 1;
        let best = self.peak.is_none_or(|p| self.smoothed > p);
        if best {
            self.peak = Some(self.smoothed);
        }
        best
    }

    /// The state saved in checkpoint `dir`, or a fresh tracker if it holds none.
    pub fn load(dir: &Path) -> Result<Self> {
        let path = dir.join(TRACKER_FILE);
        match std::fs::read_to_string(&path) {
            Ok(text) => toml::from_str(&text).map_err(|e| io_error("parsing", &path, e)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Self::default()),
            Err(e) => Err(io_error("reading", &path, e)),
        }
    }
}

/// When the best checkpoint was taken.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestInfo {
    /// The learner's gradient steps.
    pub grad_steps: u64,
    /// Training episodes observed.
    pub episodes: u64,
    /// The smoothed return that made it the best.
    pub smoothed_return: f64,
}

/// Copies the run's best checkpoint as it is now to `checkpoints/best-at-<env_steps>`
/// ([`best_at_dir`]), sealed anew; `None` (with a warning) while the run has no best policy yet.
pub fn keep_best_at(run_dir: &Path, env_steps: u64) -> Result<Option<PathBuf>> {
    let Some(best) = best_checkpoint(run_dir) else {
        tracing::warn!("{env_steps} env steps: no best policy to keep yet");
        return Ok(None);
    };
    let kept = write_atomically(&best_at_dir(run_dir, env_steps), |tmp| {
        let entries = std::fs::read_dir(&best).map_err(|e| io_error("listing", &best, e))?;
        for entry in entries {
            let from = entry.map_err(|e| io_error("listing", &best, e))?.path();
            let Some(name) = from.file_name().filter(|n| *n != MANIFEST_FILE) else {
                continue;
            };
            std::fs::copy(&from, tmp.join(name)).map_err(|e| io_error("copying", &from, e))?;
        }
        Ok(())
    })?;
    Ok(Some(kept))
}

/// Saves `algo`'s acting policy as the run's best checkpoint (replacing the last one).
pub fn write_best(
    run_dir: &Path,
    algo: &dyn Algorithm,
    agent: &ctxrace_config::AgentConfig,
    tracker: &ReturnTracker,
) -> Result<PathBuf> {
    let info = BestInfo {
        grad_steps: algo.steps(),
        episodes: tracker.episodes,
        smoothed_return: tracker.smoothed,
    };
    write_atomically(&run_dir.join(CHECKPOINTS).join(BEST_DIR), |tmp| {
        write_policy_files(tmp, algo, agent)?;
        write_toml(&tmp.join(BEST_FILE), &info)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_smoothed_return_peaks_as_the_paper_code_computes_it() {
        let mut t = ReturnTracker::default();
        let returns = [1.0, 0.0, 5.0, 5.0, -10.0, f64::NAN, 2.0];
        let best: Vec<bool> = returns.iter().map(|&r| t.observe(r)).collect();
        // ē = 1, 0.8, 1.64, 2.312, −0.1504, (NaN skipped), 0.27968
        assert_eq!(best, [true, false, true, true, false, false, false]);
        assert_eq!(t.episodes, 6);
        assert!((t.smoothed - 0.27968).abs() < 1e-12);
        assert!((t.peak.unwrap() - 2.312).abs() < 1e-12);
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(
            ReturnTracker::load(dir.path()).unwrap(),
            ReturnTracker::default()
        );
        write_toml(&dir.path().join(TRACKER_FILE), &t).unwrap();
        assert_eq!(ReturnTracker::load(dir.path()).unwrap(), t);
        // a damaged state is an error naming its file, not a fresh tracker
        std::fs::write(dir.path().join(TRACKER_FILE), "episodes = [").unwrap();
        let err = ReturnTracker::load(dir.path()).unwrap_err().to_string();
        assert!(err.contains(TRACKER_FILE), "{err}");
    }
}
