"""Tracks from Python: the names that resolve (`list`), and fetching a track from its public
repository into the per-user tracks folder, where names resolve from any folder (`download`).
The decisions (where names resolve, which repository holds a track, what loads) are Rust's,
as ``ctxrace track download`` makes them."""

from __future__ import annotations

import builtins
import os
from pathlib import Path
from typing import Optional

from ctxrace import _ctxrace
from ctxrace._env import _path


def list(tracks_dir: Optional[os.PathLike] = None) -> builtins.list:
    """The track names that resolve, each once, in the order a name resolves: those of
    `tracks_dir` (default: ``$CTXRACE_TRACKS_DIR``, else ``../shared/tracks``, else the current
    folder) and its subfolders, then those of the per-user tracks folder (``download``'s)."""
    names = [name for name, _ in _ctxrace.list_tracks(_path(tracks_dir))]
    return builtins.list(dict.fromkeys(names))


def download(name: str, source: Optional[str] = None,
             into: Optional[os.PathLike] = None) -> Path:
    """Fetches the track `name` (the paper's ``f1_esp``, ``f1_gbr``, ``f1_aut``, ``f1_mco`` from
    its repository; others, e.g. ``Monza``, from the F1TENTH racetracks) into `into` (default:
    the per-user tracks folder: ``$CTXRACE_DATA_DIR/tracks``, else
    ``$XDG_DATA_HOME/ctxrace/tracks``, else ``~/.local/share/ctxrace/tracks``), checks that it
    loads and returns its folder. `source` is a mirror's base URL with the repositories'
    layout. Raises OSError when a file cannot be fetched, ValueError for a bad name or a track
    that does not load."""
    return Path(_ctxrace.download_track(str(name), source, _path(into)))
