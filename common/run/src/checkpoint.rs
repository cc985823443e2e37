//! A checkpoint's read side, which evaluation and the Python package need without the learner:
//! the check of its seal ([`verify`]: every file's size and CRC-32 as its [`MANIFEST_FILE`]
//! lists them), a run's checkpoints ([`checkpoints`], [`latest_checkpoint`],
//! [`best_checkpoint`]) and errors naming the file. The learner writes and seals them
//! (`ctxrace_learner::checkpoint`); [`crate::trained`] reads a trained agent back.

use crate::run_dir::{BEST_DIR, CHECKPOINTS};
use std::path::{Path, PathBuf};

/// Why a checkpoint could not be written, read or trusted.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// A file or folder of the checkpoint: what was being done to it, where, and what went
    /// wrong.
    #[error("{what} {}: {reason}", path.display())]
    File {
        /// What was being done (`"reading"`, `"checking"`, ...).
        what: String,
        /// The file or folder.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// The outcome of a checkpoint operation.
pub type Result<T> = std::result::Result<T, CheckpointError>;

/// Name of the counters file in a checkpoint directory.
pub const STATE_FILE: &str = "state.toml";

/// File in every checkpoint listing its other files with their sizes and CRC-32s.
pub const MANIFEST_FILE: &str = "manifest.toml";

/// One sealed file, as its checkpoint's manifest lists it.
#[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Sealed {
    /// Its size.
    pub bytes: u64,
    /// Its CRC-32.
    pub crc32: u32,
}

/// An error naming the file (or folder) and what was being done to it.
pub fn io_error(what: &str, path: &Path, e: impl std::fmt::Display) -> CheckpointError {
    CheckpointError::File {
        what: what.to_string(),
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

/// A manifest larger than this is damaged (a real one lists a dozen files in a few hundred
/// bytes).
pub const MAX_MANIFEST_BYTES: u64 = 1 << 20;

/// Checks the seal of a checkpoint folder: its manifest lists plain file names of that folder,
/// and every file it lists is a regular file with the size (checked before reading) and CRC-32
/// listed. A folder without a manifest is unfinished or damaged and fails too.
pub fn verify(dir: &Path) -> Result<()> {
    let path = dir.join(MANIFEST_FILE);
    let text = match crate::run_dir::read_regular(&path, MAX_MANIFEST_BYTES) {
        Ok(t) => String::from_utf8_lossy(&t).into_owned(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(io_error(
                "checking",
                dir,
                format!(
                    "no {MANIFEST_FILE}, so its files cannot be verified: an unfinished or \
                     damaged checkpoint (or one written before checkpoints were sealed); \
                     choose another checkpoint or train again"
                ),
            ))
        }
        Err(e) => return Err(io_error("reading", &path, e)),
    };
    let manifest: std::collections::BTreeMap<String, Sealed> =
        toml::from_str(&text).map_err(|e| io_error("parsing", &path, e))?;
    // every file of the folder is listed (subfolders, such as an evaluation's, are not files)
    let entries = std::fs::read_dir(dir).map_err(|e| io_error("listing", dir, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| io_error("listing", dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        if !is_dir && name != MANIFEST_FILE && !manifest.contains_key(&name) {
            return Err(io_error(
                "checking",
                &entry.path(),
                "a file its manifest does not list: damaged (or added after the checkpoint \
                 was sealed; remove it)",
            ));
        }
    }
    for (name, want) in manifest {
        let plain = Path::new(&name).file_name() == Some(std::ffi::OsStr::new(&name));
        if !plain || name == MANIFEST_FILE {
            return Err(io_error(
                "checking",
                &path,
                format!("it lists '{name}', not a file of the checkpoint's folder: damaged"),
            ));
        }
        let file = dir.join(&name);
        let got = sealed(&file, want.bytes)?;
        let why = if got.bytes != want.bytes {
            format!("{} bytes, the manifest says {}", got.bytes, want.bytes)
        } else {
            format!(
                "CRC-32 {:#010x}, the manifest says {:#010x}",
                got.crc32, want.crc32
            )
        };
        if got != want {
            return Err(io_error("checking", &file, format!("{why}: damaged")));
        }
    }
    Ok(())
}

/// The size and CRC-32 of the regular file `file`; its CRC-32 only when it has `bytes` bytes
/// (0 otherwise, unused), so that a file of another size is never read.
fn sealed(file: &Path, bytes: u64) -> Result<Sealed> {
    use std::io::Read as _;
    let mut f = crate::run_dir::open_regular(file).map_err(|e| io_error("reading", file, e))?;
    let len = f
        .metadata()
        .map_err(|e| io_error("reading", file, e))?
        .len();
    if len != bytes {
        return Ok(Sealed {
            bytes: len,
            crc32: 0,
        });
    }
    let mut hasher = crc32fast::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| io_error("reading", file, e))?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(Sealed {
        bytes: len,
        crc32: hasher.finalize(),
    })
}

/// The folder of the checkpoint at gradient step `steps` in `run_dir`:
/// `checkpoints/step-<steps, 10 digits>` (zero-padded, so that names sort as steps do).
pub fn checkpoint_dir(run_dir: &Path, steps: u64) -> PathBuf {
    run_dir.join(CHECKPOINTS).join(format!("step-{steps:010}"))
}

/// The gradient step of a checkpoint folder that [`checkpoint_dir`] named (`None` for any
/// other path, `best` included).
pub fn checkpoint_step(dir: &Path) -> Option<u64> {
    dir.file_name()?
        .to_str()?
        .strip_prefix("step-")?
        .parse()
        .ok()
}

/// The complete checkpoints of a run directory, oldest first.
pub fn checkpoints(run_dir: &Path) -> Vec<std::path::PathBuf> {
    let Ok(entries) = std::fs::read_dir(run_dir.join(CHECKPOINTS)) else {
        return Vec::new();
    };
    let mut dirs: Vec<_> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| checkpoint_step(p).is_some() && p.join(STATE_FILE).exists())
        .collect();
    dirs.sort();
    dirs
}

/// The newest checkpoint of a run directory whose seal holds; damaged newer ones are passed
/// over with a warning.
pub fn latest_checkpoint(run_dir: &Path) -> Option<std::path::PathBuf> {
    checkpoints(run_dir)
        .into_iter()
        .rev()
        .find(|c| match verify(c) {
            Ok(()) => true,
            Err(e) => {
                tracing::warn!("passing over a damaged checkpoint: {e}");
                false
            }
        })
}

/// File in the run's best checkpoint saying when it was taken (the learner's `BestInfo`).
pub const BEST_FILE: &str = "best.toml";

/// The folder that keeps the run's best policy as it was when the run had taken `env_steps`
/// environment steps (`[train] keep_best_at`): `checkpoints/best-at-<env_steps>`.
pub fn best_at_dir(run_dir: &Path, env_steps: u64) -> PathBuf {
    run_dir
        .join(CHECKPOINTS)
        .join(format!("{BEST_DIR}-at-{env_steps}"))
}

/// The best checkpoint of a run directory, if it has one.
pub fn best_checkpoint(run_dir: &Path) -> Option<PathBuf> {
    let dir = run_dir.join(CHECKPOINTS).join(BEST_DIR);
    dir.join(BEST_FILE).is_file().then_some(dir)
}
