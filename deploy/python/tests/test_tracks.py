"""ctxrace.tracks: names that resolve, downloads from a mirror, bad names and no network."""

import functools
import http.server
import shutil
import threading

import pytest

import ctxrace


@pytest.fixture
def mirror(tmp_path, tracks_dir):
    """A local server with the paper repository's layout (maps/NAME.*) holding f1_gbr."""
    root = tmp_path / "mirror"
    (root / "maps").mkdir(parents=True)
    for f in ["f1_gbr.yaml", "f1_gbr.png", "f1_gbr_centerline.csv", "f1_gbr_raceline.csv"]:
        shutil.copy(tracks_dir / f, root / "maps" / f)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()


def test_a_downloaded_track_resolves_by_name_from_any_folder(tmp_path, monkeypatch, mirror):
    monkeypatch.setenv("CTXRACE_DATA_DIR", str(tmp_path / "data"))
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "f1_gbr" not in ctxrace.tracks.list(empty)
    folder = ctxrace.tracks.download("f1_gbr", source=mirror)
    assert folder == tmp_path / "data" / "tracks" / "f1_gbr"
    assert (folder / "f1_gbr.png").is_file()
    assert ctxrace.tracks.list(empty) == ["f1_gbr"]
    # the name now races, whatever folder the envs are told to look in
    env = ctxrace.RaceEnv("f1_gbr", tracks_dir=empty, rivals=1)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (108,)


def test_a_bad_name_a_missing_track_and_no_network_are_clear(tmp_path, mirror):
    with pytest.raises(ValueError, match="letters, digits"):
        ctxrace.tracks.download("../etc", into=tmp_path)
    with pytest.raises(OSError, match="Atlantis/Atlantis_map.yaml: no such file"):
        ctxrace.tracks.download("Atlantis", source=mirror, into=tmp_path)
    with pytest.raises(OSError, match="check the network connection"):
        ctxrace.tracks.download("f1_esp", source="http://127.0.0.1:1", into=tmp_path)


def test_the_paper_maps_are_listed_in_their_folder(tracks_dir):
    names = ctxrace.tracks.list(tracks_dir)
    assert {"f1_esp", "f1_gbr", "Monza"} <= set(names)
    assert len(names) == len(set(names))
