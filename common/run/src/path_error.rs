//! An I/O error on a named file or folder: what was being done, where, and the cause.

use std::path::{Path, PathBuf};

/// An I/O error while doing `what` on `path`, e.g. "writing runs/x/config.toml".
#[derive(Debug, thiserror::Error)]
#[error("{what} {}", .path.display())]
pub struct PathIoError {
    /// What was being done ("creating", "writing", …).
    pub what: &'static str,
    /// The file or folder.
    pub path: PathBuf,
    /// The cause.
    #[source]
    pub source: std::io::Error,
}

impl PathIoError {
    /// Wraps an I/O error while doing `what` on `path` (for `map_err`).
    pub fn at<'a>(what: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> Self + 'a {
        move |source| Self {
            what,
            path: path.to_path_buf(),
            source,
        }
    }
}
