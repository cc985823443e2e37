//! Tracks for Python: which names resolve ([`list_tracks`]) and fetching one from its public
//! repository into the per-user tracks folder ([`download_track`]), as `ctxrace track download`
//! does ([`ctxrace_tracks::download`]).

use crate::BindError;
use ctxrace_config::validate::Causes;
use ctxrace_tracks::download::{default_download_dir, download};
use ctxrace_tracks::files::known_tracks;
use ctxrace_tracks::{TrackError, TrackOptions};
use pyo3::exceptions::PyOSError;
use pyo3::prelude::*;
use std::path::PathBuf;

/// `(name, map yaml)` of every track a name resolves to from `tracks_dir` (none: the default
/// folder), in the order names resolve: the folder's, then the per-user folder's.
#[pyfunction]
#[pyo3(signature = (tracks_dir=None))]
pub fn list_tracks(tracks_dir: Option<PathBuf>) -> Vec<(String, PathBuf)> {
    let dir = TrackOptions::for_race(tracks_dir, false).tracks_dir;
    known_tracks(&dir)
        .into_iter()
        .map(|t| (t.name, t.yaml))
        .collect()
}

/// Downloads the track `name` into `into` (none: the per-user tracks folder) from `source`
/// (none: its public repository) with the GIL released, loads it, and returns its folder. A
/// file that cannot be fetched raises `OSError`; a bad name or a track that does not load
/// `ValueError`.
#[pyfunction]
#[pyo3(signature = (name, source=None, into=None))]
pub fn download_track(
    py: Python<'_>,
    name: &str,
    source: Option<&str>,
    into: Option<PathBuf>,
) -> PyResult<PathBuf> {
    let got = py.detach(|| {
        let into = match into {
            Some(d) => d,
            None => default_download_dir()?,
        };
        download(name, source, &into)
    });
    match got {
        Ok(d) => Ok(d.dir),
        Err(e @ TrackError::Download { .. }) => Err(PyOSError::new_err(Causes(&e).to_string())),
        Err(source) => Err(BindError::Track {
            spec: name.to_string(),
            source: Box::new(source),
        }
        .into()),
    }
}
