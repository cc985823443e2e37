//! Checkpoint files: each algorithm saves named safetensors blobs (weights and optimiser
//! moments) and a TOML file of counters into one directory; errors name the file.

use candle_core::{Error, Result};
use serde::{de::DeserializeOwned, Serialize};
use std::path::Path;

/// Name of the counters file in a checkpoint directory.
pub const STATE_FILE: &str = "state.toml";

/// An error naming the file (or folder) and what was being done to it.
pub(crate) fn io_error(what: &str, path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Msg(format!("{what} {}: {e}", path.display()))
}

/// Writes `<dir>/<name>.safetensors` for every blob and the counters `state` as
/// [`STATE_FILE`], creating `dir`.
pub fn save(dir: &Path, blobs: &[(&str, Vec<u8>)], state: &impl Serialize) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io_error("creating", dir, e))?;
    for (name, bytes) in blobs {
        let path = dir.join(format!("{name}.safetensors"));
        std::fs::write(&path, bytes).map_err(|e| io_error("writing", &path, e))?;
    }
    let path = dir.join(STATE_FILE);
    let text = toml::to_string(state).map_err(|e| io_error("serialising", &path, e))?;
    std::fs::write(&path, text).map_err(|e| io_error("writing", &path, e))
}

/// Reads `<dir>/<name>.safetensors` and hands it to `load`, naming the file in its error.
pub fn load_blob(dir: &Path, name: &str, load: impl FnOnce(&[u8]) -> Result<()>) -> Result<()> {
    let path = dir.join(format!("{name}.safetensors"));
    let bytes = std::fs::read(&path).map_err(|e| io_error("reading", &path, e))?;
    load(&bytes).map_err(|e| io_error("loading", &path, e))
}

/// Reads the counters file of a checkpoint directory.
pub fn load_state<T: DeserializeOwned>(dir: &Path) -> Result<T> {
    let path = dir.join(STATE_FILE);
    let text = std::fs::read_to_string(&path).map_err(|e| io_error("reading", &path, e))?;
    toml::from_str(&text).map_err(|e| io_error("parsing", &path, e))
}

/// Folder of a run directory that holds its checkpoints.
pub const CHECKPOINTS: &str = "checkpoints";
/// File in a checkpoint with the acting policy's weights.
pub const POLICY_FILE: &str = "policy.safetensors";
/// File in a checkpoint with the agent's configuration.
pub const AGENT_FILE: &str = "agent.toml";
/// Checkpoints kept in a run directory (older ones are removed).
const KEEP: usize = 3;

/// Saves `algo` as `<run>/checkpoints/step-<steps>/`, with the policy weights and the agent's
/// configuration beside its own files so that evaluation needs nothing else, and the smoothed
/// training return `tracker` (see [`crate::best`]). The checkpoint is written to a temporary
/// folder and renamed into place, so a crash never leaves half of one; only the newest few are
/// kept. Returns its path.
pub fn write_checkpoint(
    run_dir: &Path,
    algo: &dyn crate::Algorithm,
    agent: &ctxrace_common::AgentConfig,
    tracker: &crate::best::ReturnTracker,
) -> Result<std::path::PathBuf> {
    let root = run_dir.join(CHECKPOINTS);
    let final_dir = write_atomically(&root.join(format!("step-{:010}", algo.steps())), |tmp| {
        algo.save(tmp)?;
        write_policy_files(tmp, algo, agent)?;
        tracker.save(tmp)
    })?;
    let all = checkpoints(run_dir);
    for old in all.iter().take(all.len().saturating_sub(KEEP)) {
        std::fs::remove_dir_all(old).map_err(|e| io_error("removing", old, e))?;
    }
    Ok(final_dir)
}

/// Writes the acting policy's weights ([`POLICY_FILE`]) and the agent's configuration
/// ([`AGENT_FILE`]) into `dir`: everything evaluation needs.
pub(crate) fn write_policy_files(
    dir: &Path,
    algo: &dyn crate::Algorithm,
    agent: &ctxrace_common::AgentConfig,
) -> Result<()> {
    let policy = dir.join(POLICY_FILE);
    std::fs::write(&policy, algo.policy_weights()?).map_err(|e| io_error("writing", &policy, e))?;
    let agent_path = dir.join(AGENT_FILE);
    let text = toml::to_string(agent).map_err(|e| io_error("serialising", &agent_path, e))?;
    std::fs::write(&agent_path, text).map_err(|e| io_error("writing", &agent_path, e))
}

/// Fills a fresh temporary folder beside `final_dir` with `fill` and renames it into place,
/// replacing an earlier `final_dir`; returns `final_dir`.
pub(crate) fn write_atomically(
    final_dir: &Path,
    fill: impl FnOnce(&Path) -> Result<()>,
) -> Result<std::path::PathBuf> {
    let name = final_dir
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| Error::Msg(format!("{} has no folder name", final_dir.display())))?;
    let tmp = final_dir.with_file_name(format!(".tmp-{name}"));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| io_error("removing", &tmp, e))?;
    }
    std::fs::create_dir_all(&tmp).map_err(|e| io_error("creating", &tmp, e))?;
    fill(&tmp)?;
    if final_dir.exists() {
        std::fs::remove_dir_all(final_dir).map_err(|e| io_error("removing", final_dir, e))?;
    }
    std::fs::rename(&tmp, final_dir).map_err(|e| io_error("renaming", &tmp, e))?;
    Ok(final_dir.to_path_buf())
}

/// The complete checkpoints of a run directory, oldest first.
pub fn checkpoints(run_dir: &Path) -> Vec<std::path::PathBuf> {
    let Ok(entries) = std::fs::read_dir(run_dir.join(CHECKPOINTS)) else {
        return Vec::new();
    };
    let mut dirs: Vec<_> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("step-"))
                && p.join(STATE_FILE).exists()
        })
        .collect();
    dirs.sort();
    dirs
}

/// The newest complete checkpoint of a run directory.
pub fn latest_checkpoint(run_dir: &Path) -> Option<std::path::PathBuf> {
    checkpoints(run_dir).pop()
}
