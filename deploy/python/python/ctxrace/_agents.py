"""Multi-agent races as a PettingZoo ``ParallelEnv`` (`parallel_env`): several cars driven from
Python, the others scripted rivals scaled by the context (pure pursuit, follow-the-gap, or a
trained ctxrace agent: ``rival={"driver": "policy", "policy": RUN_DIR}``).

The agents are ``car_0`` (the ego, at the back of the grid) and ``car_1`` ... (the cars right
ahead of it); the scripted rivals start ahead of them. Each agent acts, observes and is rewarded
as the single-agent env's ego (`RaceEnv`); one that crashes or drives backwards leaves the race
(its car stays where it stopped), and the race ends for every agent when one completes the lap,
when none is left, or at the time limit (truncated). Needs ``pettingzoo`` (``pip install
pettingzoo``)."""

from __future__ import annotations

import functools
import json
import os
from typing import Any, Optional

import numpy as np
from gymnasium import spaces

from ctxrace import _ctxrace
from ctxrace._env import (
    OBS_MODES,
    PicklesAsMade,
    _COLUMNS,
    _path,
    count,
    observation_space,
    pairs_bytes,
    race_keys_json,
    render_metadata,
)

try:
    from pettingzoo import ParallelEnv as _ParallelEnv
except ImportError:  # the env needs it; the rest of the package does not
    _ParallelEnv = None


def agent_names(agents: int) -> list:
    """The agents' names, in grid order from the back: ``car_0`` is the ego."""
    return [f"car_{i}" for i in range(agents)]


class RaceParallelEnv(PicklesAsMade, _ParallelEnv or object):
    """A race of `agents` cars driven from Python and `rivals` scripted ones (see the
    module); observations in `obs_mode` as the single-agent env's, from each agent's car. It
    pickles as the arguments it was made with, so that SuperSuit's vector envs
    (``supersuit.concat_vec_envs_v1``) copy it into as many races as they step."""

    metadata = {"name": "ctxrace_race_v0", **render_metadata(_ctxrace.DEFAULT_RENDER_FPS)}

    def __init__(
        self,
        track: str = "generated:0",
        agents: int = 2,
        rivals: int = 1,
        obs_mode: str = "scan",
        context_range: float = _ctxrace.TRAIN_CONTEXT_RANGE,
        config: Optional[os.PathLike] = None,
        tracks_dir: Optional[os.PathLike] = None,
        render_mode: Optional[str] = None,
        **race_keys: Any,
    ):
        self.remember(locals(), ("track",))
        if _ParallelEnv is None:
            raise ImportError(
                "ctxrace.parallel_env needs PettingZoo: pip install pettingzoo (or pip install "
                "'ctxrace[multi]')"
            )
        if obs_mode not in OBS_MODES:
            raise ValueError(
                f"obs_mode {obs_mode!r}: use one of {', '.join(map(repr, OBS_MODES))}"
            )
        if render_mode not in (None, "rgb_array"):
            raise ValueError(
                f"render_mode {render_mode!r}: ctxrace renders 'rgb_array' (the race as an "
                f"(height, width, 3) uint8 array) or nothing (None)"
            )
        self.obs_mode = obs_mode
        self.render_mode = render_mode
        n = count("agents", agents, 1)
        self._race = _ctxrace.RaceAgents(
            str(track),
            n,
            race_keys_json(rivals, race_keys),
            _path(config),
            _path(tracks_dir),
            float(context_range),
            render_mode is not None,
        )
        self.metadata = {
            "name": "ctxrace_race_v0", **render_metadata(1.0 / self._race.decision_period)
        }
        #: The race scenario, every key resolved (``rivals`` counts every car but the ego).
        self.race_config = json.loads(self._race.race_config)
        self.possible_agents = agent_names(n)
        self.agents = []
        self._observation_space = observation_space(
            obs_mode, self._race.obs_dim, self._race.state_bounds
        )
        self._action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._seed = None

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Space:
        """Every agent's observation space (the single-agent env's in `obs_mode`)."""
        return self._observation_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Space:
        """Every agent's action: steering and speed in ``[-1, 1]``, as the ego's."""
        return self._action_space

    def reset(self, seed: Optional[int] = None, options: Optional[dict] = None):
        """Starts a race from `seed` (none: the next of the stream the first seed started);
        ``options={"context": (c_v, c_θ)}`` pins its context, else it is drawn from
        ``±context_range``. Returns (observations, infos) by agent."""
        if seed is not None:
            self._seed = np.random.default_rng(seed)
        elif self._seed is None:
            self._seed = np.random.default_rng()
        context = (options or {}).get("context")
        if context is not None:
            context = tuple(float(v) for v in np.asarray(context, dtype=np.float64))
            if len(context) != 2:
                raise ValueError(f"options['context'] must be (c_v, c_θ), not {context}")
        race_seed = int(self._seed.integers(0, 2**63))
        obs, table = self._decode(*self._race.reset(race_seed, context))
        self.agents = list(self.possible_agents)
        return obs, {a: self._info(table[i]) for i, a in enumerate(self.possible_agents)}

    def step(self, actions: dict):
        """Steps the race with each live agent's action (a missing one: standing still);
        returns (observations, rewards, terminations, truncations, infos) of the agents live
        before the step, and drops those whose episode ended."""
        if not self.agents:
            return {}, {}, {}, {}, {}
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise KeyError(f"no such agent(s) {sorted(unknown)}: the agents are {self.agents}")
        batch = np.zeros((len(self.possible_agents), 2))
        for i, a in enumerate(self.possible_agents):
            if a in actions and a in self.agents:
                batch[i] = np.asarray(actions[a], dtype=np.float64).reshape(2)
        raw = self._race.step(pairs_bytes("actions", batch, len(self.possible_agents)))
        obs, table = self._decode(*raw)
        live = [(i, a) for i, a in enumerate(self.possible_agents) if a in self.agents]
        out = (
            {a: obs[a] for _, a in live},
            {a: float(table[i, _COLUMNS["reward"]]) for i, a in live},
            {a: bool(table[i, _COLUMNS["terminated"]]) for i, a in live},
            {a: bool(table[i, _COLUMNS["truncated"]]) for i, a in live},
            {a: self._info(table[i]) for i, a in live},
        )
        self.agents = [a for _, a in live if not (out[2][a] or out[3][a])]
        return out

    def state(self) -> np.ndarray:
        """Every agent's state (its pose, speed and yaw rate, every other car relative to
        it), ``(agents, state_dim)``."""
        data = np.frombuffer(self._race.states(), dtype=np.float32)
        return data.reshape(len(self.possible_agents), self._race.state_dim).copy()

    def render(self) -> Optional[np.ndarray]:
        """The race so far as ``ctxrace race --render`` draws a moment, an ``(height, 1000, 3)``
        uint8 array (``render_mode="rgb_array"``; None without a mode): ``car_0`` drawn as the
        ego, every other car as a rival."""
        if self.render_mode is None:
            return None
        rgb, height, width = self._race.render()
        return np.frombuffer(rgb, dtype=np.uint8).reshape(height, width, 3).copy()

    def close(self):
        """Nothing to free beyond the race itself."""

    def _decode(self, obs: bytes, table: bytes):
        """(observations by agent in `obs_mode`, outcome table of one row per agent)."""
        n = len(self.possible_agents)
        scan = np.frombuffer(obs, dtype=np.float32).reshape(n, self._race.obs_dim).copy()
        table = np.frombuffer(table, dtype=np.float64).reshape(n, len(_COLUMNS))
        context = np.tile(np.asarray(self._race.context, dtype=np.float32), (n, 1))
        if self.obs_mode == "scan":
            per_agent = list(scan)
        elif self.obs_mode == "scan+context":
            per_agent = list(np.concatenate([scan, context], axis=1))
        else:
            state = self.state()
            per_agent = [
                {"scan": scan[i], "context": context[i], "state": state[i]} for i in range(n)
            ]
        return dict(zip(self.possible_agents, per_agent)), table

    def _info(self, row: np.ndarray) -> dict:
        """An agent's info: the race's context, its progress, rank change, collision with a
        car and wall crash this step."""
        return {
            "context": np.asarray(self._race.context),
            "progress": float(row[_COLUMNS["progress"]]),
            "overtakes": int(row[_COLUMNS["overtakes"]]),
            "a2a": bool(row[_COLUMNS["a2a"]]),
            "wall_crash": bool(row[_COLUMNS["wall_crash"]]),
        }


def parallel_env(
    track: str = "generated:0",
    agents: int = 2,
    rivals: int = 1,
    **kwargs: Any,
):
    """A PettingZoo ``ParallelEnv``: a race on `track` of `agents` cars driven from Python
    (``car_0`` the ego, then the cars ahead of it) and `rivals` scripted rivals. Further
    keywords: ``obs_mode`` (`OBS_MODES`), ``context_range`` (0.15), ``config`` (a race config
    TOML), ``tracks_dir`` and race keys as the TOML configs name them (``rival={"driver":
    "policy", "policy": "runs/cmask"}`` for rivals that are a trained agent)."""
    return RaceParallelEnv(track, agents, rivals, **kwargs)
