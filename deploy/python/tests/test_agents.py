"""Multi-agent races (`ctxrace.parallel_env`, PettingZoo's ParallelEnv) and rivals that are a
trained ctxrace agent (``rival={"driver": "policy", ...}``), from Python."""

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import ctxrace
from conftest import ROOT

TRACK = "generated:1"

#: A trained cMask agent of the table's records (trained on f1_esp against 1 rival).
CMASK = ROOT / "docs" / "table2" / "1r" / "cmask" / "seed10000"


@pytest.mark.parametrize("obs_mode", ctxrace.OBS_MODES)
def test_parallel_env_passes_pettingzoos_api_test(obs_mode):
    env = ctxrace.parallel_env(TRACK, agents=2, rivals=1, obs_mode=obs_mode)
    parallel_api_test(env, num_cycles=200)
    obs, infos = env.reset(seed=3)
    assert set(obs) == set(infos) == {"car_0", "car_1"} == set(env.agents)
    for agent in env.agents:
        assert env.observation_space(agent).contains(obs[agent])


def play(env, seed, steps, context=None):
    """Every step's (observations, rewards, terminations) under seeded random actions."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed, options=None if context is None else {"context": context})
    out = [obs]
    for _ in range(steps):
        if not env.agents:
            break
        actions = {a: rng.uniform(-1, 1, 2) for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)
        out.append((obs, rewards, terminations))
    return out


def test_a_race_replays_from_its_seed_and_the_agents_see_each_other():
    env = ctxrace.parallel_env(TRACK, agents=3, rivals=0, obs_mode="dict")
    first, again = play(env, 5, 60, (0.1, -0.2)), play(env, 5, 60, (0.1, -0.2))
    assert len(first) == len(again)
    for a, b in zip(first[1:], again[1:]):
        assert a[1] == b[1] and a[2] == b[2]
        for agent in a[0]:
            np.testing.assert_array_equal(a[0][agent]["scan"], b[0][agent]["scan"])
    obs = first[0]
    np.testing.assert_array_equal(obs["car_1"]["context"], np.float32([0.1, -0.2]))
    # car 0 sees car 1 right ahead; car 2, at the front, sees no car ahead of it
    assert obs["car_0"]["scan"].min() < obs["car_2"]["scan"][40:68].min()
    # each agent's state starts with its own pose; the others are relative to it
    state = env.state()
    assert state.shape == (3, 5 + 4 * 2)
    assert not np.array_equal(state[0, :2], state[1, :2])


def test_an_agent_that_crashes_leaves_and_the_others_race_on():
    env = ctxrace.parallel_env(TRACK, agents=2, rivals=0)
    env.reset(seed=0, options={"context": (0.0, 0.0)})
    left = None
    for k in range(300):
        # the ego at full lock into the wall; car 1 straight ahead, slowly
        obs, rewards, terminations, truncations, infos = env.step(
            {a: ([1.0, 1.0] if a == "car_0" else [0.0, -0.5]) for a in env.agents}
        )
        if left is None and "car_0" not in env.agents:
            assert terminations["car_0"] and infos["car_0"]["wall_crash"]
            assert rewards["car_0"] < 0
            left = k
        if left is not None and k > left + 5:
            break
    assert left is not None, "the ego never reached the wall"
    assert env.agents == ["car_1"] and set(rewards) == {"car_1"}


def test_bad_arguments_raise_naming_them():
    with pytest.raises(ValueError, match="agents must be at least 1"):
        ctxrace.parallel_env(TRACK, agents=0)
    with pytest.raises(ValueError, match="obs_mode"):
        ctxrace.parallel_env(TRACK, obs_mode="pixels")
    with pytest.raises(ValueError, match="agents = 5 and rivals = 4 make 9 cars where a race holds 8"):
        ctxrace.parallel_env(TRACK, agents=5, rivals=4)
    with pytest.raises(ValueError, match="agents = 9 and rivals = 1 make 10 cars"):
        ctxrace.make_agents_vec(TRACK, 2, agents=9)
    env = ctxrace.parallel_env(TRACK)
    env.reset(seed=0)
    with pytest.raises(KeyError, match="car_9"):
        env.step({"car_9": [0.0, 0.0]})
    with pytest.raises(ValueError, match="not finite"):
        env.step({"car_0": [np.nan, 0.0], "car_1": [0.0, 0.0]})


def test_rivals_that_are_a_trained_agent(tracks_dir):
    rival = {"driver": "policy", "policy": str(CMASK)}
    env = ctxrace.parallel_env("f1_esp", agents=1, rivals=1, tracks_dir=tracks_dir, rival=rival)
    env.reset(seed=2, options={"context": (0.0, 0.0)})
    for _ in range(15):
        env.step({"car_0": [0.0, -1.0]})  # the ego stands still; the rival drives off
    assert env.state()[0, 5 + 3] > 1.0, "the rival's speed"
    # the same rival in the single-agent env and in a race of any policy
    gym_env = ctxrace.make_vec("f1_esp", 1, rivals=1, tracks_dir=tracks_dir, rival=rival)
    gym_env.reset(seed=0)
    gym_env.step(np.zeros((1, 2)))
    result = ctxrace.race(
        lambda obs, ctx: np.float64([[0.0, 0.2]]), "f1_esp", rivals=1, seed=3,
        tracks_dir=tracks_dir, rival=rival,
    )
    assert result["steps"] > 0
    with pytest.raises(ValueError, match=r"\[rival\] policy"):
        ctxrace.parallel_env("f1_esp", tracks_dir=tracks_dir, rival={"driver": "policy"})
    with pytest.raises(ValueError, match="neither a checkpoint"):
        ctxrace.parallel_env(
            "f1_esp", tracks_dir=tracks_dir, rival={"driver": "policy", "policy": "no/such/run"}
        )


def test_the_race_renders_as_the_command_line_draws_a_moment():
    env = ctxrace.parallel_env(TRACK, agents=2, rivals=1, render_mode="rgb_array")
    env.reset(seed=1)
    for _ in range(5):
        env.step({a: [0.0, 0.0] for a in env.agents})
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape[1:] == (1000, 3)
    assert frame.std() > 0, "a picture, not a blank"
    assert env.metadata["render_fps"] == 10
    assert ctxrace.parallel_env(TRACK).render() is None
    with pytest.raises(ValueError, match="render_mode"):
        ctxrace.parallel_env(TRACK, render_mode="human")


def test_a_pickled_race_is_the_race_it_was_made_as_and_supersuit_vectorises_it():
    """A parallel env pickles as its arguments (a fresh race of the same scenario), which is how
    SuperSuit's vector envs copy it: `concat_vec_envs_v1` then steps copies of the race as one
    Gymnasium vector env of every copy's agents, copy i reset from seed + i (`black_death_v3`
    keeps an agent that left the race in the vector, observing zeros, until its race ends)."""
    import pickle

    import supersuit as ss

    env = ctxrace.parallel_env(TRACK, agents=2, rivals=1, obs_mode="scan+context", max_time=3.0)
    copy = pickle.loads(pickle.dumps(env))
    for a, b in zip(play(env, 5, 40), play(copy, 5, 40)):
        if isinstance(a, dict):
            assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
        else:
            assert all(x.keys() == y.keys() for x, y in zip(a, b))
            assert all(np.array_equal(x[k], y[k]) for x, y in zip(a, b) for k in x)
    copies = 3
    vec = ss.concat_vec_envs_v1(
        ss.pettingzoo_env_to_vec_env_v1(ss.black_death_v3(env)), copies, num_cpus=0,
        base_class="gymnasium",
    )
    assert vec.num_envs == copies * 2
    obs, _ = vec.reset(seed=11)
    assert obs.shape == (copies * 2,) + env.observation_space("car_0").shape
    for i in range(copies):
        lone, _ = ctxrace.parallel_env(
            TRACK, agents=2, rivals=1, obs_mode="scan+context", max_time=3.0
        ).reset(seed=11 + i)
        np.testing.assert_array_equal(obs[2 * i], lone["car_0"])
        np.testing.assert_array_equal(obs[2 * i + 1], lone["car_1"])
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(80):
        obs, rewards, terminations, truncations, _ = vec.step(
            rng.uniform(-1, 1, (vec.num_envs, 2)).astype(np.float32)
        )
        assert np.isfinite(obs).all() and np.isfinite(rewards).all()
        ended += int(np.sum(terminations | truncations))
    assert ended > 0


def test_make_agents_vec_steps_each_race_as_the_simulators_with_black_death():
    """The races of `make_agents_vec` (stepped in Rust, race-major envs) are the multi-agent
    races of simulator seeds seed + i that `parallel_env` steps, agent for agent; an agent that
    left its race observes a zero scan with reward 0 and no flag until the race ends, when all
    of its envs end."""
    import json
    import pickle

    from ctxrace import _ctxrace

    races, agents, keys = 3, 2, dict(rivals=1, max_time=3.0)
    vec = ctxrace.make_agents_vec(TRACK, races, agents, obs_mode="scan+context", threads=2, **keys)
    assert vec.num_envs == races * agents
    obs, info = vec.reset(seed=11)
    lones = [_ctxrace.RaceAgents(TRACK, agents, json.dumps(keys)) for _ in range(races)]

    def decode(out):
        scans, table = out
        return (np.frombuffer(scans, np.float32).reshape(agents, -1),
                np.frombuffer(table, np.float64).reshape(agents, -1))

    for i, lone in enumerate(lones):
        scans, _ = decode(lone.reset(11 + i))
        np.testing.assert_array_equal(obs[i * agents:(i + 1) * agents, :-2], scans)
        np.testing.assert_array_equal(obs[i * agents, -2:], np.float32(lone.context))
    rng = np.random.default_rng(0)
    ended, black, dead = np.zeros(races, bool), 0, np.zeros(races * agents, bool)
    restarted = np.full(races, -1)
    for _ in range(40):
        actions = rng.uniform(-1, 1, (races * agents, 2))
        actions[0], actions[1] = [1.0, 1.0], [0.0, -0.5]  # race 0: the ego into the wall
        obs, reward, terminated, truncated, info = vec.step(actions)
        for i, lone in enumerate(lones):
            rows = slice(i * agents, (i + 1) * agents)
            if ended[i] and restarted[i] < 0:
                # the step after its race ended starts every one of its envs again
                assert not (reward[rows].any() or (terminated | truncated)[rows].any())
                np.testing.assert_array_equal(info["context"][rows.start], info["context"][rows][1])
                restarted[i] = 1
            if ended[i]:
                continue
            scans, table = decode(lone.step(actions[rows].tobytes()))
            np.testing.assert_array_equal(obs[rows, :-2], scans)
            np.testing.assert_array_equal(reward[rows], table[:, 0])
            for a, k in enumerate(range(rows.start, rows.stop)):
                if lone.finished:
                    assert terminated[k] or truncated[k]
                elif dead[k]:
                    assert not (terminated[k] or truncated[k] or scans[a].any() or reward[k])
                    black += 1
                else:
                    assert (terminated[k], truncated[k]) == (table[a, 1] != 0, table[a, 2] != 0)
                dead[k] |= table[a, 1] != 0
            ended[i] = lone.finished
    assert (restarted == 1).all() and black > 0, (restarted, black)
    copy = pickle.loads(pickle.dumps(vec))
    assert copy.num_envs == vec.num_envs
    np.testing.assert_array_equal(copy.reset(seed=11)[0], vec.reset(seed=11)[0])
    with pytest.raises(ValueError, match="agents must be at least 1"):
        ctxrace.make_agents_vec(TRACK, 2, agents=0)
