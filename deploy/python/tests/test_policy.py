"""`ctxrace.load_policy`: a trained agent acts from Python as the command line's does, in a race
and in the evaluation protocol; bad paths and inputs raise."""

import csv
import json
import subprocess

import numpy as np
import pytest

import ctxrace
from conftest import ROOT

#: A sealed cMask checkpoint of small networks (testdata/d6b5c40/README.md).
CHECKPOINT = ROOT / "testdata" / "d6b5c40" / "cmask" / "checkpoint"


@pytest.mark.parametrize("act", ["mode", "sample"])
def test_a_trained_agent_drives_the_race_the_command_line_drives(tmp_path, ctxrace_bin, act):
    trace = tmp_path / "trace.csv"
    subprocess.run(
        [ctxrace_bin, "race", "generated:0", "--policy", CHECKPOINT, "--act", act,
         "--context", "0.1,-0.2", "--seed", "3", "--trace", trace],
        check=True, capture_output=True,
    )
    with open(trace) as f:
        rows = list(csv.DictReader(f))
    policy = ctxrace.load_policy(CHECKPOINT)
    assert policy.algo == "cmask" and policy.obs_dim == 108
    env = ctxrace.RaceEnv("generated:0")
    context = np.array([0.1, -0.2])
    obs, _ = env.reset(seed=3, options={"context": context})
    policy.reset(seeds=[3])
    for row in rows[1:]:
        action = policy.act(obs, context, deterministic=act == "mode")
        assert action.tolist() == [float(row["action_steer"]), float(row["action_speed"])]
        obs, _, terminated, truncated, _ = env.step(action)
    assert terminated or truncated


def test_a_trained_agent_evaluates_as_the_command_line_evaluates(tmp_path, ctxrace_bin):
    out = tmp_path / "eval"
    subprocess.run(
        [ctxrace_bin, "eval", CHECKPOINT, "--track", "generated:0", "--rivals", "1",
         "--grid", "2", "--laps", "2", "--workers", "1", "--out", out],
        check=True, capture_output=True,
    )
    cli = json.loads((out / "contexts.json").read_text())
    mine = ctxrace.evaluate(ctxrace.load_policy(CHECKPOINT), "generated:0", rivals=1, grid=2,
                            laps=2, batch=3)
    assert mine.contexts == cli


def test_batches_rows_and_bad_inputs():
    policy = ctxrace.load_policy(CHECKPOINT)
    obs = np.random.default_rng(0).uniform(0, 1, size=(4, 108)).astype(np.float32)
    contexts = np.zeros((4, 2))
    policy.reset(rows=range(4), seeds=range(4))
    batch = policy.act(obs, contexts, deterministic=True)
    assert batch.shape == (4, 2) and (np.abs(batch) <= 1).all()
    policy.reset(rows=[2], seeds=[2])
    alone = policy.act(obs[2], contexts[2], deterministic=True, rows=[2])
    np.testing.assert_array_equal(alone, batch[2])
    with pytest.raises(ValueError, match=r"shape \(k, 108\)"):
        policy.act(obs[:, :50], contexts)
    with pytest.raises(TypeError, match="floating-point"):
        policy.act(obs.astype(np.int32), contexts)
    with pytest.raises(ValueError, match="NaN"):
        policy.act(np.full((1, 108), np.nan), contexts[:1])
    with pytest.raises(ValueError, match="distinct"):
        policy.act(obs[:2], contexts[:2], rows=[1, 1])
    with pytest.raises(ValueError, match="neither a checkpoint"):
        ctxrace.load_policy(ROOT / "configs")
    with pytest.raises(ValueError, match="not best, latest, step-N"):
        ctxrace.load_policy(CHECKPOINT, checkpoint="newest")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, ctxrace_bin):
    """A cMask run of 300 decisions (testdata/tiny-cmask.toml: generated:0, one rival, 20-s
    races) trained on contexts within ±0.1, so that its race differs from `evaluate`'s
    defaults (f1_esp, 3 rivals, ±0.15)."""
    folder = tmp_path_factory.mktemp("tiny")
    cfg = folder / "tiny.toml"
    text = (ROOT / "testdata" / "tiny-cmask.toml").read_text()
    cfg.write_text(text.replace("[train]\n", "[train]\ncontext_range = 0.1\n"))
    run = folder / "run"
    subprocess.run([ctxrace_bin, "train", cfg, "--inline", "--run-dir", run],
                   check=True, capture_output=True)
    return run


def eval_cli(ctxrace_bin, out, source, *args):
    """`ctxrace eval SOURCE ARGS` on one worker into `out`: its contexts.json rows."""
    subprocess.run([ctxrace_bin, "eval", source, *args, "--workers", "1", "--out", out],
                   check=True, capture_output=True)
    return json.loads((out / "contexts.json").read_text())


def test_a_trained_run_evaluates_on_its_own_race_unless_told_otherwise(tmp_path, ctxrace_bin,
                                                                       tiny_run):
    policy = ctxrace.load_policy(tiny_run)
    assert policy.track == "generated:0" and policy.context_range == 0.1
    assert policy.race_config["rivals"] == 1 and policy.race_config["max_time"] == 20.0
    # the run's track, rival, race and training range, as `ctxrace eval RUN` takes them
    mine = ctxrace.evaluate(policy, grid=5, laps=1, batch=4)
    assert mine.contexts == eval_cli(ctxrace_bin, tmp_path / "own", tiny_run, "--grid", "5",
                                     "--laps", "1")
    # within ±0.1 only the centre of the ±0.3 grid of 5 (±0.15 would add 8 more)
    assert sum(r["in_distribution"] for r in mine.contexts) == 1
    # arguments given win
    told = ctxrace.evaluate(policy, "generated:1", rivals=2, train_range=0.3, grid=2, laps=1)
    assert told.contexts == eval_cli(ctxrace_bin, tmp_path / "told", tiny_run, "--track",
                                     "generated:1", "--rivals", "2", "--train-range", "0.3",
                                     "--grid", "2", "--laps", "1")
    # race keys are laid over the run's race: 0.3-s races of 0.1-s decisions
    short = ctxrace.evaluate(policy, grid=2, laps=1, max_time=0.3)
    assert all(e["steps"] <= 3 for e in short.episodes)
    assert max(e["steps"] for e in mine.episodes) > 3
    # a race file replaces the run's race but not its rivals, in Python as in `ctxrace eval`
    race = tmp_path / "race.toml"
    race.write_text("max_time = 0.5\nrivals = 3\n")
    filed = ctxrace.evaluate(policy, config=race, grid=2, laps=1)
    assert filed.contexts == eval_cli(ctxrace_bin, tmp_path / "filed", tiny_run, "--config",
                                      str(race), "--grid", "2", "--laps", "1")
    assert all(e["steps"] <= 5 for e in filed.episodes)
    # a checkpoint alone knows no run: the function's defaults
    assert ctxrace.load_policy(CHECKPOINT).track is None


def test_a_race_from_python_is_the_command_lines_race_and_draws_it(tmp_path, ctxrace_bin):
    out = subprocess.run(
        [ctxrace_bin, "race", "generated:0", "--policy", CHECKPOINT, "--context", "0.1,-0.2",
         "--seed", "3", "--json"],
        check=True, capture_output=True,
    )
    cli = json.loads(out.stdout)
    gif = tmp_path / "race.gif"
    mine = ctxrace.race(ctxrace.load_policy(CHECKPOINT), "generated:0", context=(0.1, -0.2),
                        seed=3, render=gif)
    for key in ["progress", "overtakes", "a2a", "wall_crash", "steps", "episode_return",
                "ended_by"]:
        assert mine[key] == cli[key], key
    assert gif.read_bytes()[:4] == b"GIF8"
    # a callable drives too; a picture by its extension, a bad one refused by name
    still = ctxrace.race(lambda obs, ctx: np.zeros((1, 2)), rivals=2, render=tmp_path / "r.png")
    assert still["steps"] > 0 and (tmp_path / "r.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="gif"):
        ctxrace.race(lambda obs, ctx: np.zeros((1, 2)), render=tmp_path / "r.bmp")
    with pytest.raises(TypeError, match="callable"):
        ctxrace.race(3)


def mlp_forward(layers, x):
    """The MLP policy file's action, computed in numpy: tanh between layers, clipped output."""
    for i, (w, b) in enumerate(layers):
        x = w @ x + b
        if i < len(layers) - 1:
            x = np.tanh(x)
    return np.clip(x, -1, 1)


def test_a_python_mlp_policy_races_and_evaluates_from_the_command_line(tmp_path, tracks_dir, ctxrace_bin):
    rng = np.random.default_rng(4)
    layers = [
        (rng.normal(0, 0.3, (16, 110)), rng.normal(0, 0.1, 16)),
        (rng.normal(0, 0.3, (2, 16)), np.array([0.0, 0.6])),
    ]
    path = tmp_path / "policy.safetensors"
    ctxrace.save_mlp_policy(path, layers, activation="tanh", inputs="scan+context")
    trace = tmp_path / "trace.csv"
    subprocess.run(
        [ctxrace_bin, "race", "f1_esp", "--policy", path, "--rivals", "1", "--context",
         "0.2,-0.1", "--seed", "5", "--trace", trace, "--tracks-dir", tracks_dir],
        check=True, capture_output=True,
    )
    with open(trace) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) > 3
    scan = lambda row: np.array([float(row[f"scan{b}"]) for b in range(108)])
    for before, row in zip(rows, rows[1:]):
        want = mlp_forward(layers, np.concatenate([scan(before), [0.2, -0.1]]))
        got = np.array([float(row["action_steer"]), float(row["action_speed"])])
        np.testing.assert_allclose(got, want, atol=1e-4)
    # the protocol, from the file's name
    out = tmp_path / "eval"
    subprocess.run(
        [ctxrace_bin, "eval", path, "--track", "f1_esp", "--rivals", "1", "--laps", "1",
         "--grid", "3", "--out", out, "--tracks-dir", tracks_dir],
        check=True, capture_output=True,
    )
    with open(out / "contexts.csv") as f:
        assert len(list(csv.DictReader(f))) == 9


def test_an_mlp_policy_that_cannot_act_is_refused_before_writing(tmp_path):
    path = tmp_path / "p.safetensors"
    with pytest.raises(ValueError, match="gives 3 values"):
        ctxrace.save_mlp_policy(path, [(np.zeros((3, 108)), np.zeros(3))])
    with pytest.raises(ValueError, match="layer 0 takes 110 inputs where 108 arrive"):
        ctxrace.save_mlp_policy(path, [(np.zeros((2, 110)), np.zeros(2))])
    with pytest.raises(ValueError, match="'gelu' is none of tanh, relu, silu"):
        ctxrace.save_mlp_policy(path, [(np.zeros((2, 108)), np.zeros(2))], activation="gelu")
    with pytest.raises(ValueError, match="not finite"):
        ctxrace.save_mlp_policy(path, [(np.full((2, 108), np.nan), np.zeros(2))])
    assert not path.exists()
