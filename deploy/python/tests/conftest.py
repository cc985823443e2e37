"""Fixtures: the paper's maps and the ctxrace binary the checks compare against."""

import os
from pathlib import Path

import pytest

#: The repository's root.
ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="session")
def tracks_dir() -> Path:
    """The folder of the paper's maps: $CTXRACE_TRACKS_DIR, else ../shared/tracks beside the
    repository."""
    d = Path(os.environ.get("CTXRACE_TRACKS_DIR", ROOT.parent / "shared" / "tracks"))
    if not (d / "f1_esp.yaml").is_file():
        pytest.fail(f"the paper's maps are not in {d}: set CTXRACE_TRACKS_DIR to their folder")
    return d


@pytest.fixture(scope="session")
def ctxrace_bin() -> Path:
    """The command line: $CTXRACE_BIN, else target/release/ctxrace."""
    b = Path(os.environ.get("CTXRACE_BIN", ROOT / "target" / "release" / "ctxrace"))
    if not b.is_file():
        pytest.fail(f"no ctxrace binary at {b}: build it with `cargo build --release`")
    return b
