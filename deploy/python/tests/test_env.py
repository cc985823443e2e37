"""The Gymnasium envs: spaces, reset/step/autoreset, contexts, seeds, threads, race keys,
tracks, and every bad input raising a Python exception."""

import csv
import subprocess
import threading

import gymnasium
import numpy as np
import pytest
from gymnasium.error import ClosedEnvironmentError, ResetNeeded
from gymnasium.vector import AutoresetMode
from gymnasium.utils.env_checker import check_env

import ctxrace

TRACK = "generated:0"


def random_actions(env, steps, seed=0):
    """`steps` batches of uniform random actions for `env`."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, size=(steps, env.num_envs, 2))


def rollout(env, actions, seed, options=None):
    """Every step's (obs, reward, terminated, info) under `actions` from `reset(seed)`."""
    obs, info = env.reset(seed=seed, options=options)
    out = [(obs, np.zeros(env.num_envs), np.zeros(env.num_envs, bool), info)]
    for a in actions:
        obs, reward, terminated, _, info = env.step(a)
        out.append((obs, reward, terminated, info))
    return out


def test_import_registers_a_race_that_passes_check_env():
    env = gymnasium.make("ctxrace/Race-v0", track=TRACK, rivals=2)
    check_env(env.unwrapped)
    obs, info = env.reset(seed=3)
    assert obs.shape == (108,) and obs.dtype == np.float32
    assert set(info) == {"context", "progress", "overtakes", "a2a", "wall_crash"}
    env.close()


def test_gymnasium_make_vec_builds_the_rust_vector_env():
    for mode in (None, "vector_entry_point"):
        envs = gymnasium.make_vec(
            "ctxrace/Race-v0", num_envs=4, vectorization_mode=mode, track=TRACK, rivals=2
        )
        assert isinstance(envs, ctxrace.RaceVectorEnv), mode
        assert envs.num_envs == 4 and envs.race_config["rivals"] == 2
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (4, 108)
    # Gymnasium's own vectorisation of the single env still works
    sync = gymnasium.make_vec("ctxrace/Race-v0", num_envs=2, vectorization_mode="sync")
    assert sync.num_envs == 2 and not isinstance(sync, ctxrace.RaceVectorEnv)


def test_observation_modes_add_the_context_and_the_state():
    for mode in ("scan+context", "dict"):
        check_env(gymnasium.make("ctxrace/Race-v0", track=TRACK, rivals=2, obs_mode=mode).unwrapped)
    actions = random_actions(ctxrace.make_vec(TRACK, 3), 60)
    runs = {
        mode: rollout(ctxrace.make_vec(TRACK, 3, rivals=2, obs_mode=mode), actions, seed=4)
        for mode in ("scan", "scan+context", "dict")
    }
    for (scan, _, _, info), (both, *_), (d, *_) in zip(*runs.values()):
        # the same race in every mode: the scan, then the episode's context, then the state
        np.testing.assert_array_equal(both[:, :108], scan)
        np.testing.assert_array_equal(both[:, 108:], info["context"].astype(np.float32))
        np.testing.assert_array_equal(d["scan"], scan)
        np.testing.assert_array_equal(d["context"], info["context"].astype(np.float32))
        assert d["state"].shape == (3, 5 + 4 * 2) and np.isfinite(d["state"]).all()
        # the rivals start ahead of the ego on the grid, and headings are wrapped
        assert (np.abs(d["state"][:, [7, 11]]) <= np.pi).all()
    first_state = runs["dict"][0][0]["state"]
    assert (first_state[:, 5] > 0).all() and (first_state[:, 3] >= 0).all()
    with pytest.raises(ValueError, match="obs_mode"):
        ctxrace.make_vec(TRACK, 1, obs_mode="pixels")


def test_same_step_autoreset_keeps_the_final_state_of_dict_observations():
    envs = ctxrace.make_vec(
        TRACK, 4, obs_mode="dict", autoreset_mode=AutoresetMode.SAME_STEP, max_time=1.0
    )
    envs.reset(seed=1)
    for a in random_actions(envs, 40):
        obs, _, terminated, truncated, info = envs.step(a)
        ended = terminated | truncated
        if ended.any():
            final = info["final_obs"]
            assert set(final) == {"scan", "context", "state"}
            np.testing.assert_array_equal(
                final["context"][ended], info["final_info"]["context"][ended].astype(np.float32)
            )
            # the ended episodes' states, not the new ones' (which start on the grid)
            assert np.isfinite(final["state"][ended]).all()
            assert (final["state"][ended, :2] != obs["state"][ended, :2]).any()
            return
    pytest.fail("no episode ended in 40 steps of 1 s races")


def test_vector_spaces_and_arrays():
    env = ctxrace.make_vec(TRACK, 4, rivals=2, seed=1)
    assert env.single_observation_space.shape == (108,)
    assert env.action_space.shape == (4, 2)
    obs, info = env.reset()
    assert obs.shape == (4, 108) and obs.dtype == np.float32
    assert obs in env.observation_space
    assert info["context"].shape == (4, 2)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert reward.shape == (4,) and reward.dtype == np.float64
    assert terminated.dtype == bool and truncated.dtype == bool
    for key in ("progress", "overtakes", "a2a", "wall_crash"):
        assert info[key].shape == (4,)
    assert env.race_config["rivals"] == 2
    env.close()


def test_ended_episodes_reset_on_the_next_step_with_a_fresh_context():
    env = ctxrace.make_vec(TRACK, 8, seed=2)
    env.reset()
    full_left = np.tile([-1.0, 1.0], (8, 1))
    for _ in range(200):
        _, _, terminated, truncated, info = env.step(full_left)
        if terminated.any():
            break
    assert terminated.any(), "full lock at full speed meets a wall"
    ended = terminated | truncated
    before = info["context"].copy()
    obs, reward, terminated, truncated, info = env.step(full_left)
    assert (reward[ended] == 0).all() and not terminated[ended].any()
    assert (info["progress"][ended] == 0).all()
    assert (info["context"][ended] != before[ended]).all()
    assert (np.abs(info["context"]) <= 0.15).all()
    env.close()


def test_same_step_autoreset_is_next_step_without_the_reset_step():
    """Gymnasium's SAME_STEP: the ending step returns the next episode's first observation and
    reset info, the ended one's last observation and step info under final_obs / final_info;
    the races are those of NEXT_STEP with its reset steps left out."""
    same_mode = gymnasium.vector.AutoresetMode.SAME_STEP
    same = ctxrace.make_vec(TRACK, 3, seed=4, autoreset_mode=same_mode)
    next_ = ctxrace.make_vec(TRACK, 3, seed=4)
    assert same.metadata["autoreset_mode"] == same_mode
    obs_s, _ = same.reset()
    obs_n, _ = next_.reset()
    action = np.tile([-0.3, 0.9], (3, 1))
    ends = 0
    for _ in range(150):
        obs_s, reward_s, term_s, trunc_s, info_s = same.step(action)
        obs_n, reward_n, term_n, trunc_n, info_n = next_.step(action)
        np.testing.assert_array_equal(reward_s, reward_n)
        np.testing.assert_array_equal(term_s | trunc_s, term_n | trunc_n)
        ended = term_n | trunc_n
        if ended.any():
            ends += 1
            assert (info_s["_final_obs"] == ended).all() and (info_s["_final_info"] == ended).all()
            np.testing.assert_array_equal(info_s["final_obs"][ended], obs_n[ended])
            np.testing.assert_array_equal(
                info_s["final_info"]["progress"][ended], info_n["progress"][ended]
            )
            assert (info_s["progress"][ended] == 0).all()
            # the step NEXT_STEP spends on the reset (the other envs go one step further there,
            # so the comparison ends here)
            obs_n, _, _, _, info_n = next_.step(action)
            np.testing.assert_array_equal(obs_s[ended], obs_n[ended])
            np.testing.assert_array_equal(info_s["context"][ended], info_n["context"][ended])
            break
        np.testing.assert_array_equal(obs_s, obs_n)
    assert ends == 1, "full speed at a steady lock meets a wall within 150 steps"
    with pytest.raises(ValueError, match="NEXT_STEP or AutoresetMode.SAME_STEP"):
        ctxrace.make_vec(TRACK, 2, autoreset_mode="sometimes")
    same.close()
    next_.close()


def test_contexts_pinned_at_reset_stay_for_later_episodes():
    env = ctxrace.make_vec(TRACK, 3, seed=0)
    pinned = np.array([[0.3, -0.3], [0.0, 0.2], [-0.25, 0.1]])
    _, info = env.reset(options={"context": pinned})
    np.testing.assert_array_equal(info["context"], pinned)
    for _ in range(150):
        _, _, _, _, info = env.step(np.tile([-1.0, 1.0], (3, 1)))
    np.testing.assert_array_equal(info["context"], pinned)
    _, info = env.reset(seed=5)
    assert (np.abs(info["context"]) <= 0.15).all(), "a reset without contexts draws again"
    narrow = ctxrace.make_vec(TRACK, 16, context_range=0.05)
    _, info = narrow.reset(seed=1)
    assert (np.abs(info["context"]) <= 0.05).all() and len(np.unique(info["context"])) > 16


def test_same_seed_and_actions_give_the_same_races_on_any_threads():
    actions = random_actions(ctxrace.make_vec(TRACK, 5), 120)
    runs = [
        rollout(ctxrace.make_vec(TRACK, 5, rivals=1, threads=t), actions, seed=9)
        for t in (1, 2, 2)
    ]
    for other in runs[1:]:
        for (o1, r1, t1, i1), (o2, r2, t2, i2) in zip(runs[0], other):
            np.testing.assert_array_equal(o1, o2)
            np.testing.assert_array_equal(r1, r2)
            np.testing.assert_array_equal(i1["context"], i2["context"])
    other_seed = rollout(ctxrace.make_vec(TRACK, 5), actions[:1], seed=10)
    assert not np.array_equal(other_seed[0][0], runs[0][0][0])


def test_env_i_of_a_vector_is_the_lone_race_seeded_seed_plus_i():
    vec = ctxrace.make_vec(TRACK, 3)
    lone = ctxrace.RaceEnv(TRACK)
    contexts = np.array([[0.1, 0.1], [0.2, -0.1], [-0.3, 0.0]])
    vobs, _ = vec.reset(seed=20, options={"context": contexts})
    lobs, _ = lone.reset(seed=22, options={"context": contexts[2]})
    np.testing.assert_array_equal(vobs[2], lobs)
    for a in random_actions(vec, 40):
        vobs, vr, vt, _, _ = vec.step(a)
        lobs, lr, lt, _, _ = lone.step(a[2])
        np.testing.assert_array_equal(vobs[2], lobs)
        assert (vr[2], vt[2]) == (lr, lt)
        if lt:
            break


def test_python_threads_step_their_own_envs_at_once():
    actions = random_actions(ctxrace.make_vec(TRACK, 4), 60)
    alone = rollout(ctxrace.make_vec(TRACK, 4, threads=1), actions, seed=4)[-1][0]
    results = {}

    def run(k):
        results[k] = rollout(ctxrace.make_vec(TRACK, 4, threads=1), actions, seed=4)[-1][0]

    workers = [threading.Thread(target=run, args=(k,)) for k in range(3)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    for k in range(3):
        np.testing.assert_array_equal(results[k], alone)


def test_race_keys_presets_and_config_files(tmp_path):
    env = ctxrace.make_vec(TRACK, 1, preset="paper-code", rival={"driver": "follow-the-gap"})
    assert env.race_config["min_speed"] == 1.0
    assert env.race_config["rival"]["driver"] == "follow-the-gap"
    config = tmp_path / "race.toml"
    config.write_text('max_time = 30.0\n[lidar]\nbeams = 54\n')
    env = ctxrace.make_vec(TRACK, 2, config=config, max_speed=5)
    assert env.single_observation_space.shape == (54,)
    assert env.race_config["max_time"] == 30.0 and env.race_config["max_speed"] == 5.0
    with pytest.raises(ValueError, match="no_such_key"):
        ctxrace.make_vec(TRACK, 1, no_such_key=1)
    with pytest.raises(ValueError, match="rivals"):
        ctxrace.make_vec(TRACK, 1, rivals=12)


def test_tracks_by_name_yaml_path_and_generated(tracks_dir):
    by_name = ctxrace.make_vec("f1_esp", 1, tracks_dir=tracks_dir)
    by_path = ctxrace.make_vec(str(tracks_dir / "f1_esp.yaml"), 1)
    a, _ = by_name.reset(seed=0)
    b, _ = by_path.reset(seed=0)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="unknown track 'no_such_track'"):
        ctxrace.make_vec("no_such_track", 1, tracks_dir=tracks_dir)
    with pytest.raises(ValueError, match="generated"):
        ctxrace.make_vec("generated:x", 1)


def test_bad_actions_raise_and_step_nothing():
    env = ctxrace.make_vec(TRACK, 2, seed=0)
    obs, _ = env.reset()
    with pytest.raises(ValueError, match=r"shape \(2, 2\)"):
        env.step(np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"shape \(2, 2\)"):
        env.step(np.zeros(4))
    with pytest.raises(TypeError, match="floating-point"):
        env.step(np.zeros((2, 2), dtype=np.int64))
    with pytest.raises(TypeError, match="floating-point"):
        env.step([["a", "b"], ["c", "d"]])
    with pytest.raises(ValueError, match="env 1 .* not finite"):
        env.step(np.array([[0.0, 0.0], [np.nan, 0.0]]))
    with pytest.raises(ValueError, match="not finite"):
        env.step(np.array([[np.inf, 0.0], [0.0, 0.0]]))
    again, _ = env.reset(seed=None)
    env.step(np.zeros((2, 2), dtype=np.float32))


def test_bad_contexts_seeds_and_sizes_raise():
    env = ctxrace.make_vec(TRACK, 2)
    with pytest.raises(ValueError, match=r"\[-0.9, 0.9\]"):
        env.reset(seed=0, options={"context": [[0.0, 0.0], [1.5, 0.0]]})
    with pytest.raises(ValueError, match=r"shape \(2, 2\)"):
        env.reset(seed=0, options={"context": [0.1, 0.1]})
    with pytest.raises(ValueError, match="not finite"):
        env.reset(seed=0, options={"context": [[0.0, np.nan], [0.0, 0.0]]})
    with pytest.raises(gymnasium.error.Error, match="Seed"):
        env.reset(seed=-1)
    with pytest.raises(ValueError, match="num_envs"):
        ctxrace.make_vec(TRACK, 0)
    with pytest.raises(ValueError, match="context_range"):
        ctxrace.make_vec(TRACK, 1, context_range=2.0)
    with pytest.raises(RuntimeError, match="call reset first"):
        ctxrace.make_vec(TRACK, 1).step(np.zeros((1, 2)))
    # every count names its argument; numpy integers are integers
    for kwargs, error, name in [
        (dict(num_envs=2.5), TypeError, "num_envs"),
        (dict(num_envs=True), TypeError, "num_envs"),
        (dict(num_envs=1, threads=-3), ValueError, "threads"),
        (dict(num_envs=1, rivals=-1), ValueError, "rivals"),
        (dict(num_envs=1, rivals="2"), TypeError, "rivals"),
    ]:
        with pytest.raises(error, match=name):
            ctxrace.make_vec(TRACK, **kwargs)
    assert ctxrace.make_vec(TRACK, np.int64(3), threads=np.int32(1)).num_envs == 3


def test_vector_get_attr_and_call_give_a_value_per_env():
    envs = ctxrace.make_vec(TRACK, 3, rivals=2, render_mode="rgb_array")
    envs.reset(seed=0, options={"context": [[0.1, 0.0], [0.0, 0.2], [-0.1, -0.1]]})
    np.testing.assert_array_equal(np.array(envs.get_attr("context")), [[0.1, 0.0], [0.0, 0.2], [-0.1, -0.1]])
    assert envs.get_attr("race_config") == (envs.race_config,) * 3
    assert envs.get_attr("observation_space") == (envs.single_observation_space,) * 3
    assert envs.call("render_mode") == ("rgb_array",) * 3
    frames = envs.call("render")
    assert len(frames) == 3 and frames[0].ndim == 3
    with pytest.raises(AttributeError, match="get_attr"):
        envs.call("step", np.zeros((3, 2)))
    with pytest.raises(AttributeError):
        envs.get_attr("no_such_attribute")


def test_envs_pickle_as_the_arguments_they_were_made_with():
    import pickle

    vec = ctxrace.make_vec(TRACK, 2, rivals=2, seed=5, max_time=9.0)
    again = pickle.loads(pickle.dumps(vec))
    assert type(again) is ctxrace.RaceVectorEnv and again.num_envs == 2
    assert again.race_config == vec.race_config and again.race_config["max_time"] == 9.0
    actions = random_actions(vec, 20)
    for a, b in zip(rollout(vec, actions, seed=5), rollout(again, actions, seed=5)):
        np.testing.assert_array_equal(a[0], b[0])
    lone = pickle.loads(pickle.dumps(ctxrace.RaceEnv(TRACK, rivals=2)))
    assert lone.race_config["rivals"] == 2
    assert isinstance(ctxrace.__version__, str) and ctxrace.__version__.count(".") == 2


def test_closed_and_ended_envs_raise():
    env = ctxrace.make_vec(TRACK, 1, seed=0)
    env.reset()
    env.close()
    with pytest.raises(ClosedEnvironmentError):
        env.step(np.zeros((1, 2)))
    with pytest.raises(ClosedEnvironmentError):
        env.reset()
    lone = ctxrace.RaceEnv(TRACK)
    with pytest.raises(ResetNeeded):
        lone.step(np.zeros(2))
    lone.reset(seed=1)
    terminated = False
    while not terminated:
        _, _, terminated, truncated, _ = lone.step(np.array([-1.0, 1.0]))
        terminated |= truncated
    with pytest.raises(ResetNeeded):
        lone.step(np.zeros(2))
    lone.close()
    with pytest.raises(ClosedEnvironmentError):
        lone.reset()


def test_replaying_the_command_lines_trace_drives_the_same_race(tmp_path, tracks_dir, ctxrace_bin):
    trace = tmp_path / "trace.csv"
    for ego in ("random", "pure-pursuit"):
        subprocess.run(
            [ctxrace_bin, "race", "f1_esp", "--rivals", "1", "--context", "0.2,-0.1",
             "--ego", ego, "--seed", "7", "--trace", trace, "--tracks-dir", tracks_dir],
            check=True, capture_output=True,
        )
        with open(trace) as f:
            rows = list(csv.DictReader(f))
        env = ctxrace.RaceEnv("f1_esp", rivals=1, tracks_dir=tracks_dir)
        obs, _ = env.reset(seed=7, options={"context": (0.2, -0.1)})
        scan = lambda row: np.array([float(row[f"scan{b}"]) for b in range(108)])
        np.testing.assert_allclose(obs, scan(rows[0]), atol=6e-6)
        for row in rows[1:]:
            action = np.array([float(row["action_steer"]), float(row["action_speed"])])
            obs, reward, terminated, truncated, _ = env.step(action)
            np.testing.assert_allclose(obs, scan(row), atol=6e-6)
            assert abs(reward - float(row["reward"])) < 6e-7
        assert terminated or truncated, f"{ego}: the trace ends with the episode"
        assert len(rows) > (100 if ego == "pure-pursuit" else 2)
