"""ctxrace.sb3.VecEnv: SB3's VecEnv contract (spaces, same-step autoreset, terminal
observations, seeds, options, attributes, render), its episode statistics against the ctxrace
envs stepped with the same seeds and actions, and SB3 training on it (PPO, MultiInputPolicy,
VecNormalize, VecFrameStack)."""

import numpy as np
import pytest

pytest.importorskip(
    "stable_baselines3",
    reason="Stable-Baselines3 is not installed (CI leaves it and its torch, about 3 GB from PyPI, "
    "out): pip install torch --index-url https://download.pytorch.org/whl/cpu, then pip install "
    "stable-baselines3",
)

import gymnasium  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402
from stable_baselines3.common.logger import KVWriter, Logger  # noqa: E402
from stable_baselines3.common.monitor import Monitor  # noqa: E402
from stable_baselines3.common.vec_env import VecFrameStack, VecNormalize  # noqa: E402

import ctxrace  # noqa: E402
from ctxrace.sb3 import VecEnv  # noqa: E402

#: A race key that ends episodes within 20 decisions (the time limit, s), so that random actions
#: see laps' worth of episode ends: crashes (terminated) and time limits (truncated).
SHORT = {"max_time": 2.0}
OBS_MODES = ("scan", "scan+context", "dict")


def actions(env, steps, seed=0):
    """`steps` batches of uniform random actions for `env`, float32 as SB3 passes them."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, size=(steps, env.num_envs, 2)).astype(np.float32)


def row(obs, i):
    """Env `i`'s observation of a batch (an array or a dict of arrays)."""
    return {k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i]


def assert_obs_equal(a, b):
    """Two observations (arrays or dicts of arrays) equal."""
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    else:
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("mode", OBS_MODES)
def test_reset_and_step_give_what_the_spaces_say(mode):
    env = VecEnv(num_envs=3, obs_mode=mode, **SHORT)
    single = ctxrace.make_vec("generated:0", 1, obs_mode=mode).single_observation_space
    assert env.observation_space == single and env.num_envs == 3
    assert isinstance(env.observation_space, gymnasium.spaces.Dict) == (mode == "dict")
    obs = env.reset()
    for i in range(3):
        assert env.observation_space.contains(row(obs, i))
    assert len(env.reset_infos) == 3 and "context" in env.reset_infos[0]
    obs, rewards, dones, infos = env.step(actions(env, 1)[0])
    assert all(env.observation_space.contains(row(obs, i)) for i in range(3))
    assert rewards.shape == (3,) and rewards.dtype == np.float32
    assert dones.shape == (3,) and dones.dtype == bool
    assert len(infos) == 3
    assert {"context", "progress", "overtakes", "a2a", "wall_crash", "TimeLimit.truncated"} <= set(
        infos[0]
    )
    env.close()


@pytest.mark.parametrize("mode", OBS_MODES)
def test_episodes_equal_the_ctxrace_envs_stepped_with_the_same_seed_and_actions(mode):
    n, seed = 3, 11
    env = VecEnv(num_envs=n, obs_mode=mode, **SHORT)
    reference = ctxrace.make_vec(
        "generated:0", n, obs_mode=mode, autoreset_mode=AutoresetMode.SAME_STEP, **SHORT
    )
    assert env.seed(seed) == [seed + i for i in range(n)]
    assert_obs_equal(env.reset(), reference.reset(seed=seed)[0])
    returns, lengths = np.zeros(n), np.zeros(n, int)
    episodes = [[] for _ in range(n)]
    ends = {"terminated": 0, "truncated": 0}
    for a in actions(env, 60):
        obs, rewards, dones, infos = env.step(a)
        r_obs, r_rewards, terminated, truncated, r_info = reference.step(a)
        assert_obs_equal(obs, r_obs)
        np.testing.assert_array_equal(rewards, r_rewards.astype(np.float32))
        np.testing.assert_array_equal(dones, terminated | truncated)
        stepped = r_info.get("final_info", r_info)
        returns += r_rewards
        lengths += 1
        for i in range(n):
            assert infos[i]["TimeLimit.truncated"] == (truncated[i] and not terminated[i])
            assert infos[i]["progress"] == stepped["progress"][i]
            if not dones[i]:
                assert "episode" not in infos[i] and "terminal_observation" not in infos[i]
                continue
            ends["truncated" if infos[i]["TimeLimit.truncated"] else "terminated"] += 1
            assert_obs_equal(infos[i]["terminal_observation"], row(r_info["final_obs"], i))
            episode = infos[i]["episode"]
            assert episode["r"] == pytest.approx(returns[i], abs=1e-9)
            assert episode["l"] == lengths[i] and "overtakes" not in episode
            assert episode["progress"] == stepped["progress"][i]
            assert episode["a2a"] == stepped["a2a"][i]
            assert episode["wall_crash"] == stepped["wall_crash"][i]
            np.testing.assert_array_equal(episode["context"], stepped["context"][i])
            assert episode["t"] >= 0
            # the next episode started: its context in reset_infos, as the vector env's
            np.testing.assert_array_equal(env.reset_infos[i]["context"], r_info["context"][i])
            episodes[i].append(episode)
            returns[i], lengths[i] = 0.0, 0
    assert ends["terminated"] > 0 and ends["truncated"] > 0, ends
    # each env's first episode is the single env's from reset seed `seed + i`
    for i in range(n):
        single = gymnasium.make("ctxrace/Race-v0", obs_mode=mode, **SHORT).unwrapped
        single.reset(seed=seed + i)
        total, steps = 0.0, 0
        for a in actions(env, 60):
            _, reward, terminated, truncated, _ = single.step(a[i])
            total, steps = total + reward, steps + 1
            if terminated or truncated:
                break
        assert (episodes[i][0]["r"], episodes[i][0]["l"]) == (pytest.approx(total), steps)


def test_seeds_and_options_as_sb3_sets_them():
    env = VecEnv(num_envs=2)
    env.seed(5)
    first = env.reset()
    assert env._seeds == [None, None]  # used once, as SB3's own VecEnvs do
    env.seed(5)
    np.testing.assert_array_equal(env.reset(), first)
    assert not np.array_equal(env.reset(), first)  # unseeded: drawn from the env's generator
    env.set_options({"context": (0.1, -0.2)})
    env.reset()
    for context in env.get_attr("context"):
        np.testing.assert_allclose(context, (0.1, -0.2))
    np.testing.assert_allclose(env.reset_infos[1]["context"], (0.1, -0.2))
    env.set_options([{"context": (0.0, 0.0)}, {"context": (0.2, 0.2)}])
    env.reset()
    np.testing.assert_allclose(np.stack(env.get_attr("context")), [[0, 0], [0.2, 0.2]])
    env._seeds = [1, 7]
    with pytest.raises(ValueError, match="seeded together"):
        env.reset()
    env._reset_seeds()
    for options, message in (
        ({"laps": 2}, "only 'context'"),
        ([{"context": (0, 0)}, {}], "every env's context"),
    ):
        env.set_options(options)
        with pytest.raises(ValueError, match=message):
            env.reset()


def test_attributes_methods_and_render_delegate_to_the_vector_env():
    env = VecEnv(num_envs=2, rivals=2, render_mode="rgb_array")
    assert env.render_mode == "rgb_array" and env.metadata["render_fps"] == 10.0
    assert [c["rivals"] for c in env.get_attr("race_config")] == [2, 2]
    assert len(env.get_attr("context", indices=[1])) == 1
    assert env.has_attr("race_config") and not env.has_attr("no_such_attribute")
    with pytest.raises(AttributeError, match="one scenario"):
        env.set_attr("rivals", 3)
    assert env.env_is_wrapped(Monitor) == [False, False]
    assert env.env_is_wrapped(Monitor, indices=1) == [False]
    env.reset()
    env.step(actions(env, 1)[0])
    pictures = env.env_method("render")
    assert len(pictures) == 2 and pictures[0].dtype == np.uint8 and pictures[0].shape[2] == 3
    assert len(env.env_method("render", indices=[0])) == 1
    with pytest.raises(AttributeError, match="render"):
        env.env_method("reset")
    tiled = env.render()
    height, width, _ = pictures[0].shape
    assert tiled.shape == (2 * height, width, 3)
    env.close()
    with pytest.warns(UserWarning, match="render_mode"):  # no render mode: SB3 draws nothing
        assert VecEnv(num_envs=1).render() is None


def test_made_from_a_vector_env_or_keywords():
    made = ctxrace.make_vec("generated:0", 2, rivals=2, autoreset_mode=AutoresetMode.SAME_STEP)
    env = VecEnv(made)
    assert env.env is made and env.num_envs == 2
    with pytest.raises(ValueError, match="SAME_STEP"):
        VecEnv(ctxrace.make_vec("generated:0", 2))
    with pytest.raises(ValueError, match="SAME_STEP"):
        VecEnv(num_envs=2, autoreset_mode=AutoresetMode.NEXT_STEP)
    with pytest.raises(TypeError, match="not both"):
        VecEnv(made, num_envs=2)
    with pytest.raises(TypeError, match="keywords"):
        VecEnv("generated:0")
    assert VecEnv(num_envs=2, autoreset_mode=AutoresetMode.SAME_STEP).num_envs == 2


class Records(KVWriter):
    """An SB3 logger output that keeps every dump."""

    def __init__(self):
        self.dumps = []

    def write(self, key_values, key_excluded, step=0):
        self.dumps.append(dict(key_values))

    def close(self):
        pass


class Episodes(BaseCallback):
    """Collects the episode statistics of the infos SB3's rollouts see."""

    def __init__(self):
        super().__init__()
        self.episodes = []

    def _on_step(self):
        self.episodes += [info["episode"] for info in self.locals["infos"] if "episode" in info]
        return True


def test_ppo_trains_and_logs_the_episode_returns():
    env = VecEnv(num_envs=4, **SHORT)
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
    records, episodes = Records(), Episodes()
    model.set_logger(Logger(None, [records]))
    model.learn(256, callback=episodes)
    assert model.num_timesteps == 256 and len(records.dumps) == 1
    logged = records.dumps[-1]
    assert episodes.episodes and len(model.ep_info_buffer) == len(episodes.episodes)
    assert logged["rollout/ep_rew_mean"] == pytest.approx(
        np.mean([e["r"] for e in episodes.episodes])
    )
    assert logged["rollout/ep_len_mean"] == pytest.approx(
        np.mean([e["l"] for e in episodes.episodes])
    )
    # the seed reproduces the run
    again = PPO("MlpPolicy", VecEnv(num_envs=4, **SHORT), n_steps=64, batch_size=64,
                n_epochs=1, seed=0, device="cpu")
    again.set_logger(Logger(None, [Records()]))
    again.learn(256)
    assert [e["r"] for e in again.ep_info_buffer] == [e["r"] for e in model.ep_info_buffer]


def test_multi_input_policy_trains_on_dict_observations():
    env = VecEnv(num_envs=2, obs_mode="dict", **SHORT)
    model = PPO("MultiInputPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0,
                device="cpu")
    model.learn(128)
    assert len(model.ep_info_buffer) > 0
    action, _ = model.predict(env.reset(), deterministic=True)
    assert action.shape == (2, 2) and env.action_space.contains(action[0])


@pytest.mark.parametrize("mode", ["scan", "dict"])
def test_vec_normalize_and_vec_frame_stack_wrap_it(mode):
    env = VecFrameStack(VecNormalize(VecEnv(num_envs=2, obs_mode=mode, **SHORT)), n_stack=4)
    obs = env.reset()
    scan = obs["scan"] if mode == "dict" else obs
    assert scan.shape == (2, 4 * 108)
    ended = 0
    for a in actions(env, 30):
        obs, rewards, dones, infos = env.step(a)
        for i in np.flatnonzero(dones):
            ended += 1
            last = infos[i]["terminal_observation"]
            last = last["scan"] if mode == "dict" else last
            assert last.shape == (4 * 108,) and "episode" in infos[i]
    assert ended > 0
    # VecNormalize saw the episodes' raw returns: its running return statistics moved
    assert env.venv.ret_rms.count > 1
