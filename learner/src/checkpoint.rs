//! Checkpoint files: each algorithm saves named safetensors blobs (weights and optimiser
//! moments) and a TOML file of counters into one directory; errors name the file.

use candle_core::{Error, Result};
use serde::{de::DeserializeOwned, Serialize};
use std::path::Path;

/// Name of the counters file in a checkpoint directory.
pub const STATE_FILE: &str = "state.toml";

fn io_error(what: &str, path: &Path, e: impl std::fmt::Display) -> Error {
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
