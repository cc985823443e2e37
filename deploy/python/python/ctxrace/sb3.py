"""ctxrace's vector env as a Stable-Baselines3 ``VecEnv`` (`VecEnv`), with each finished
episode's statistics in its info as SB3's ``VecMonitor`` writes them, so that SB3's logger shows
``rollout/ep_rew_mean`` without a wrapper.

Needs Stable-Baselines3 (``pip install stable-baselines3``, or the package's extra ``sb3``),
which needs torch; a CPU-only torch is enough: ``pip install torch --index-url
https://download.pytorch.org/whl/cpu`` first, where PyPI's default wheel pulls about 3 GB of
CUDA libraries. ``import ctxrace`` imports neither."""

from __future__ import annotations

import time
from typing import Any, List, Optional, Sequence, Type

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode

from ctxrace._env import RaceVectorEnv

try:
    from stable_baselines3.common.vec_env import VecEnv as _VecEnv
    from stable_baselines3.common.vec_env.base_vec_env import (
        VecEnvIndices,
        VecEnvObs,
        VecEnvStepReturn,
    )
except ImportError as e:
    raise ImportError(
        "ctxrace.sb3 needs Stable-Baselines3: pip install stable-baselines3 (it needs torch; "
        "for a CPU-only torch instead of PyPI's default with about 3 GB of CUDA libraries, "
        "first: pip install torch --index-url https://download.pytorch.org/whl/cpu)"
    ) from e

__all__ = ["VecEnv"]

#: Info entries of the vector env that are no per-env step info.
_NOT_PER_ENV = ("final_obs", "final_info")


def _per_env(info: dict) -> List[dict]:
    """Gymnasium's vector info (a dict of arrays, one row per env) as SB3's list of dicts, one
    per env; the masks (``_key``) and same-step autoreset's entries left out."""
    columns = {
        key: value.tolist() if value.ndim == 1 else list(value)
        for key, value in info.items()
        if not key.startswith("_") and key not in _NOT_PER_ENV
    }
    return [dict(zip(columns, row)) for row in zip(*columns.values())]


def _row(obs: Any, i: int) -> Any:
    """Env `i`'s observation (an array or a dict of arrays) of a batch."""
    if isinstance(obs, dict):
        return {key: value[i] for key, value in obs.items()}
    return obs[i]


class VecEnv(_VecEnv):
    """ctxrace's vector env (`ctxrace.RaceVectorEnv`, stepped in Rust) as Stable-Baselines3's
    ``VecEnv``, for ``PPO("MlpPolicy", ctxrace.sb3.VecEnv(track="f1_esp", num_envs=16))``
    (``MultiInputPolicy`` for ``obs_mode="dict"``).

    Made from the keywords ``gymnasium.make_vec("ctxrace/Race-v0", ...)`` takes (``track``,
    ``num_envs``, ``rivals``, ``obs_mode``, ``render_mode``, race keys such as ``max_time``,
    ...; defaults as there), or around a vector env `env` made with
    ``autoreset_mode=AutoresetMode.SAME_STEP``. SB3's contract: `reset` returns the
    observations; `step_wait` returns (observations, float32 rewards, dones, infos) where an env
    whose episode ended has already started its next one (its first observation returned, its
    reset info in ``reset_infos``) and its info holds the ended episode's last observation
    (``terminal_observation``) and ``TimeLimit.truncated`` (it hit the time limit, not a lap's
    end, a crash or a collision). Each info holds the env's step info (``context``,
    ``progress``, ``overtakes``, ``a2a``, ``wall_crash``).

    Episode statistics: the info of an env whose episode ended holds ``episode``, as SB3's
    ``VecMonitor`` writes it: ``r`` (its return), ``l`` (its steps) and ``t`` (seconds since
    this VecEnv was made), and the race's metrics as its last step reports them: ``progress``
    (PG), ``a2a`` and ``wall_crash`` (what ended it) and ``context`` (its ``(c_v, c_θ)``). An
    episode's overtakes are the race's to count (its preset decides whether the last step's
    count): ``ctxrace.evaluate`` reports them.

    Seeds as SB3 sets them: ``seed(S)`` makes the next `reset` start env ``i`` from the
    simulator's reset seed ``S + i`` (the vector env's ``reset(seed=S)``);
    ``set_options({"context": (c_v, c_θ)})`` (or a list of one such dict per env) pins the
    contexts of the episodes from the next `reset` on, until a `reset` without options.
    """

    def __init__(self, env: Optional[RaceVectorEnv] = None, **make_vec_kwargs: Any):
        if env is None:
            mode = make_vec_kwargs.pop("autoreset_mode", AutoresetMode.SAME_STEP)
            if mode != AutoresetMode.SAME_STEP:
                raise ValueError(
                    f"autoreset_mode {mode!r}: SB3's VecEnv resets an env in the step that ended "
                    "it, AutoresetMode.SAME_STEP (the default here)"
                )
            env = RaceVectorEnv(autoreset_mode=AutoresetMode.SAME_STEP, **make_vec_kwargs)
        elif make_vec_kwargs:
            raise TypeError(
                "give either a ctxrace vector env or the keywords to make one, not both "
                f"(got {', '.join(make_vec_kwargs)})"
            )
        elif not isinstance(env, RaceVectorEnv):
            raise TypeError(
                f"env must be a ctxrace.RaceVectorEnv, not {type(env).__name__}; make one from "
                "keywords: ctxrace.sb3.VecEnv(track=..., num_envs=..., ...)"
            )
        elif env.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError(
                "SB3's VecEnv resets an env in the step that ended it: make the vector env with "
                "autoreset_mode=AutoresetMode.SAME_STEP"
            )
        #: The ctxrace vector env stepped.
        self.env: RaceVectorEnv = env
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
        self.metadata["render_fps"] = env.metadata["render_fps"]
        self._actions: Optional[np.ndarray] = None
        self._t_start = time.time()
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=np.int64)

    def _vector_seed(self) -> Optional[int]:
        """The vector env's reset seed for the seeds SB3's ``seed(S)`` set (``S + i``, env by
        env), or None where none was set."""
        seeds = self._seeds
        if all(s is None for s in seeds):
            return None
        if seeds[0] is None or list(seeds) != [seeds[0] + i for i in range(self.num_envs)]:
            raise ValueError(
                f"seeds {seeds}: ctxrace's envs are seeded together, env i from S + i, as "
                "seed(S) sets them"
            )
        return int(seeds[0])

    def _vector_options(self) -> Optional[dict]:
        """The vector env's reset options for those SB3's ``set_options`` set: every env's
        context pinned, or none."""
        options = self._options
        if not any(options):
            return None
        unknown = {key for o in options for key in o} - {"context"}
        if unknown:
            raise ValueError(
                f"reset options {sorted(unknown)}: ctxrace's envs take only 'context'"
            )
        if not all(options):
            raise ValueError("pin every env's context with set_options, or none")
        return {"context": np.array([o["context"] for o in options], dtype=np.float64)}

    def reset(self) -> VecEnvObs:
        """Starts every env's next episode (from the seeds and options set since the last
        reset, then forgotten) and returns the observations; the reset infos go to
        ``reset_infos`` and the episode statistics start over."""
        obs, info = self.env.reset(seed=self._vector_seed(), options=self._vector_options())
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = _per_env(info)
        self._returns[:] = 0.0
        self._lengths[:] = 0
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        """Keeps the actions, ``(num_envs, 2)`` in [-1, 1], for `step_wait`."""
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        """Steps every env with the actions of `step_async`: (observations, float32 rewards,
        dones, infos), an ended env restarted (see the class)."""
        obs, reward, terminated, truncated, info = self.env.step(self._actions)
        dones = terminated | truncated
        # under same-step autoreset, final_info holds every env's step info, the ended included
        stepped = info.get("final_info", info)
        self._returns += reward
        self._lengths += 1
        infos = _per_env(stepped)
        for i, time_limit in enumerate((truncated & ~terminated).tolist()):
            infos[i]["TimeLimit.truncated"] = time_limit
        ended = np.flatnonzero(dones)
        if len(ended):
            restarted = _per_env(info)
            seconds = round(time.time() - self._t_start, 6)
            for i in ended:
                step_info = infos[i]
                step_info["terminal_observation"] = _row(info["final_obs"], i)
                step_info["episode"] = {
                    "r": float(self._returns[i]),
                    "l": int(self._lengths[i]),
                    "t": seconds,
                    "progress": step_info["progress"],
                    "a2a": step_info["a2a"],
                    "wall_crash": step_info["wall_crash"],
                    "context": step_info["context"],
                }
                self.reset_infos[i] = restarted[i]
            self._returns[ended] = 0.0
            self._lengths[ended] = 0
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        """Frees the races."""
        self.env.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> List[Any]:
        """Each env's attribute `attr_name` (see `ctxrace.RaceVectorEnv.get_attr`: ``context``
        per env, the single env's spaces, ``race_config``, ``render_mode``, ...); an
        AttributeError where there is none."""
        values = list(self.env.get_attr(attr_name))
        if indices is None:
            return values
        return [values[i] for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Raises AttributeError: the races are stepped together in Rust with one scenario,
        fixed when the vector env is made."""
        raise AttributeError(
            f"cannot set {attr_name!r}: ctxrace's races share one scenario, fixed when the env "
            "is made; make a new VecEnv with the keywords to change"
        )

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> List[Any]:
        """Each env's `method_name` called, as `ctxrace.RaceVectorEnv.call` calls it (only
        ``render`` is a method an env has by itself)."""
        values = list(self.env.call(method_name, *method_args, **method_kwargs))
        if indices is None:
            return values
        return [values[i] for i in self._get_indices(indices)]

    def env_is_wrapped(
        self, wrapper_class: Type[gymnasium.Wrapper], indices: VecEnvIndices = None
    ) -> List[bool]:
        """False for each env: the races are no Gymnasium envs, so none is wrapped."""
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[Optional[np.ndarray]]:
        """Every env's race so far as ``(height, width, 3)`` uint8 pictures (with
        ``render_mode="rgb_array"``; Nones without); `render` tiles them into one."""
        return list(self.env.render() or (None,) * self.num_envs)
