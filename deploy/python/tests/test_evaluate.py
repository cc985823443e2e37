"""`ctxrace.evaluate`: the rows of `ctxrace eval` for a reference policy, the same rows from a
Python policy acting as that policy, and bad arguments raising."""

import json
import subprocess

import numpy as np
import pytest

import ctxrace

KEYS = ("context_speed", "context_steer", "in_distribution", "laps", "progress", "overtakes",
        "a2a", "wall_crash", "lap_complete", "episode_return")


def test_reference_rows_equal_the_command_lines(tmp_path, tracks_dir, ctxrace_bin):
    out = tmp_path / "eval"
    subprocess.run(
        [ctxrace_bin, "eval", "pure-pursuit", "--track", "f1_esp", "--rivals", "1",
         "--grid", "3", "--laps", "2", "--workers", "2", "--out", out,
         "--tracks-dir", tracks_dir],
        check=True, capture_output=True,
    )
    cli = json.loads((out / "contexts.json").read_text())
    py = ctxrace.evaluate("pure-pursuit", "f1_esp", rivals=1, grid=3, laps=2,
                          tracks_dir=tracks_dir)
    assert len(py.contexts) == 9 and len(py.episodes) == 18
    assert [{k: r[k] for k in KEYS} for r in py.contexts] == [{k: r[k] for k in KEYS} for r in cli]
    inside = py.means(in_distribution=True)
    assert inside["contexts"] == 1 and 0 < inside["progress"] <= 1
    assert py.means(in_distribution=False)["contexts"] == 8


def test_a_python_policy_gets_the_rows_of_the_policy_it_acts_as():
    calls = []

    def still(obs, context):
        calls.append(len(obs))
        assert obs.shape[1] == 108 and context.shape == (len(obs), 2)
        return np.tile([0.0, -1.0], (len(obs), 1))

    args = dict(track="generated:0", rivals=2, grid=2, range=0.2, laps=3, seed=4, max_time=20.0)
    mine = ctxrace.evaluate(still, batch=5, **args)
    reference = ctxrace.evaluate("still", **args)
    assert mine.contexts == reference.contexts
    assert mine.episodes == reference.episodes
    assert max(calls) == 5
    assert [r["in_distribution"] for r in mine.contexts] == [False] * 4


def test_bad_evaluations_raise():
    with pytest.raises(ValueError, match="unknown reference policy"):
        ctxrace.evaluate("fast", track="generated:0")
    with pytest.raises(TypeError, match="callable"):
        ctxrace.evaluate(3, track="generated:0")
    with pytest.raises(ValueError, match="grid 0"):
        ctxrace.evaluate("still", track="generated:0", grid=0)
    with pytest.raises(ValueError, match=r"shape \(1, 2\)"):
        ctxrace.evaluate(lambda o, c: np.zeros((len(o), 3)), track="generated:0", grid=1,
                         laps=1)
    with pytest.raises(ValueError, match="not finite"):
        ctxrace.evaluate(lambda o, c: np.full((len(o), 2), np.nan), track="generated:0",
                         grid=1, laps=1)


def test_ctrl_c_stops_a_reference_evaluation_soon():
    """An interrupt (Ctrl-C) during a long reference evaluation raises KeyboardInterrupt within
    a chunk of episodes, not when the whole grid is done."""
    import _thread
    import signal
    import threading
    import time

    # Python's own Ctrl-C handler, whatever the process was started with: a process started in
    # the background by a shell (`cmd &`) inherits SIGINT ignored, and interrupt_main then does
    # nothing (the grid ran to its end and the test failed, run from `nohup ... &`)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        timer = threading.Timer(0.5, _thread.interrupt_main)
        start = time.monotonic()
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            ctxrace.evaluate("pure-pursuit", "generated:0", rivals=1, grid=7, laps=200, threads=1)
        timer.cancel()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert time.monotonic() - start < 10.0
