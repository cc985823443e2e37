"""The race as Gymnasium envs: one race (`RaceEnv`, registered as ``ctxrace/Race-v0``) and many
stepped together on Rust worker threads (`RaceVectorEnv`, from `make_vec`)."""

from __future__ import annotations

import functools
import json
import operator
import os
from typing import Any, Optional

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.error import ClosedEnvironmentError, ResetNeeded
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ctxrace import _ctxrace

#: The columns of the outcome table the extension hands back, one row per env.
_COLUMNS = {name: i for i, name in enumerate(_ctxrace.OUTCOME_COLUMNS)}

#: Largest magnitude of a context element the simulator takes (its own constant).
CONTEXT_LIMIT = _ctxrace.CONTEXT_LIMIT


def count(name: str, value: Any, least: int) -> int:
    """`value` as a Python int of at least `least` (numpy integers included), or an error that
    names the argument `name`."""
    if isinstance(value, bool):
        raise TypeError(f"{name} must be an integer, not {value!r}")
    try:
        n = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be an integer, not {value!r}") from None
    if n < least:
        raise ValueError(f"{name} must be at least {least}, not {n}")
    return n


class PicklesAsMade:
    """An env that pickles as the arguments it was made with: unpickled, it is a fresh env to
    reset (the race's state stays in its process). Its ``__init__`` starts with
    ``self.remember(locals(), positional)``."""

    def remember(self, arguments: dict, positional: tuple) -> None:
        """Keeps ``__init__``'s `arguments` (its ``locals()`` before anything else): the
        `positional` names' values, the others (race keys spread out) as keywords."""
        keywords = {
            k: v
            for k, v in arguments.items()
            if k not in ("self", "race_keys", "__class__") and k not in positional
        }
        keywords.update(arguments.get("race_keys", {}))
        self._made_with = (tuple(arguments[k] for k in positional), keywords)

    def __reduce__(self):
        args, keywords = self._made_with
        return (functools.partial(type(self), **keywords), args)


def race_keys_json(rivals: Optional[int], race_keys: dict) -> str:
    """The race keys as the extension reads them: a JSON object (``None`` values left out,
    ``rivals`` set unless None)."""
    keys = {k: v for k, v in race_keys.items() if v is not None}
    if rivals is not None:
        keys["rivals"] = count("rivals", rivals, 0)
    try:
        return json.dumps(keys)
    except TypeError as e:
        raise TypeError(
            f"race keys must be numbers, strings, booleans or dicts of them, as the TOML configs "
            f"take them: {e}"
        ) from None


def _path(path: Optional[os.PathLike]) -> Optional[str]:
    """A path as the extension takes it."""
    return None if path is None else os.fspath(path)


def pairs_bytes(what: str, values: Any, n: int) -> bytes:
    """`values` checked as an ``(n, 2)`` array of finite floats, as float64 bytes."""
    a = np.asarray(values)
    if a.dtype.kind != "f":
        raise TypeError(
            f"{what} must be floating-point (float32 or float64), not dtype {a.dtype}"
        )
    if a.shape != (n, 2):
        raise ValueError(f"{what} must have shape ({n}, 2), not {a.shape}")
    if not np.isfinite(a).all():
        bad = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
        raise ValueError(f"{what} of env {bad} is {a[bad].tolist()}: not finite")
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def contexts_bytes(contexts: Any, n: int) -> bytes:
    """Per-env contexts checked (shape ``(n, 2)``, each value in ±CONTEXT_LIMIT) as bytes."""
    data = pairs_bytes("context", contexts, n)
    c = np.frombuffer(data, dtype=np.float64)
    if np.abs(c).max() > CONTEXT_LIMIT:
        raise ValueError(
            f"context values must lie in [-{CONTEXT_LIMIT}, {CONTEXT_LIMIT}] (the paper trains on "
            f"±0.15 and evaluates on ±0.3), got {c.reshape(n, 2).tolist()}"
        )
    return data


def render_metadata(render_fps: float) -> dict:
    """An env's render keys of ``metadata``: ``rgb_array`` at `render_fps` frames a second."""
    return {"render_modes": ["rgb_array"], "render_fps": render_fps}


class Races:
    """The extension's `RaceVector` with its outputs decoded into numpy arrays, recording each
    env's race to draw it when `render_mode` is ``rgb_array``; with several `agents` a race,
    its rows ("envs") are the races' agents, race-major."""

    def __init__(
        self,
        track: str,
        num_envs: int,
        rivals: int,
        tracks_dir: Optional[os.PathLike],
        config: Optional[os.PathLike],
        context_range: float,
        threads: int,
        race_keys: dict,
        same_step: bool,
        render_mode: Optional[str],
        obs_mode: str = "scan",
        agents: int = 1,
    ):
        if obs_mode not in OBS_MODES:
            raise ValueError(
                f"obs_mode {obs_mode!r}: use one of {', '.join(map(repr, OBS_MODES))}"
            )
        self.obs_mode = obs_mode
        num_envs = count("num_envs", num_envs, 1)
        agents = count("agents", agents, 1)
        threads = count("threads", threads, 0)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(
                f"render_mode {render_mode!r}: ctxrace renders 'rgb_array' (the race as an "
                f"(height, width, 3) uint8 array) or nothing (None)"
            )
        self.render_mode = render_mode
        self.inner = _ctxrace.RaceVector(
            str(track),
            num_envs,
            race_keys_json(rivals, race_keys),
            _path(config),
            _path(tracks_dir),
            float(context_range),
            threads,
            same_step,
            render_mode is not None,
            agents,
        )
        #: Rows of observations, actions and outcomes: races x agents.
        self.num_envs = self.inner.num_envs
        self.races, self.agents = num_envs, agents
        self.obs_dim = self.inner.obs_dim
        #: The race scenario, every key resolved.
        self.race_config = json.loads(self.inner.race_config)
        #: The render keys of an env's ``metadata``: a frame per decision.
        self.metadata = render_metadata(1.0 / self.inner.decision_period)
        self._started = False
        #: One env's observation space in `obs_mode`.
        self.single_observation_space = observation_space(
            obs_mode, self.obs_dim, self.inner.state_bounds
        )

    def decode(self, obs: bytes, table: bytes):
        """(observations in `obs_mode`, outcome table) of one row per env."""
        scan = np.frombuffer(obs, dtype=np.float32).reshape(self.num_envs, self.obs_dim).copy()
        table = np.frombuffer(table, dtype=np.float64).reshape(self.num_envs, len(_COLUMNS))
        contexts = None if self.obs_mode == "scan" else self.contexts()
        return self.observation(scan, contexts, ended=False), table

    def observation(self, scan: np.ndarray, contexts: Optional[np.ndarray], ended: bool):
        """The observations of `obs_mode` from the scans and contexts (one row per env), with
        the current states or (`ended`) those the episodes that ended at the last step ended in."""
        if self.obs_mode == "scan":
            return scan
        context = contexts.astype(np.float32)
        if self.obs_mode == "scan+context":
            return np.concatenate([scan, context], axis=1)
        state = np.frombuffer(self.inner.states(ended), dtype=np.float32)
        state = state.reshape(self.num_envs, self.inner.state_dim).copy()
        return {"scan": scan, "context": context, "state": state}

    def reset(self, seed: int, contexts: Any = None):
        """Starts every env's next episode (see `RaceVectorEnv.reset`)."""
        c = None if contexts is None else contexts_bytes(contexts, self.races)
        out = self.decode(*self.inner.reset(seed, c))
        self._started = True
        return out

    def step(self, actions: Any):
        """Steps every env (see `RaceVectorEnv.step`)."""
        return self.decode(*self.inner.step(pairs_bytes("actions", actions, self.num_envs)))

    def final_obs(self, contexts: np.ndarray):
        """Under same-step autoreset, the last observations (in `obs_mode`) of the episodes that
        ended at the last step, whose contexts were `contexts` (one row per env; the other rows
        are stale)."""
        data = np.frombuffer(self.inner.final_obs(), dtype=np.float32)
        scan = data.reshape(self.num_envs, self.obs_dim).copy()
        return self.observation(scan, contexts, ended=True)

    def contexts(self) -> np.ndarray:
        """Each env's current episode's context, ``(num_envs, 2)`` (its race's)."""
        races = np.frombuffer(self.inner.contexts(), dtype=np.float64).reshape(self.races, 2)
        return races if self.agents == 1 else np.repeat(races, self.agents, axis=0)

    def render(self) -> Optional[list]:
        """Every env's race so far as ``(height, width, 3)`` uint8 pictures, the moments of
        ``ctxrace race --render race.gif`` (as wide as its frames: 1000 pixels); None without a
        render mode."""
        if self.render_mode is None:
            return None
        if not self._started:
            raise ResetNeeded("nothing to draw before the first reset: call reset")
        pictures = []
        for env in range(self.num_envs):
            rgb, height, width = self.inner.render(env)
            pictures.append(np.frombuffer(rgb, dtype=np.uint8).reshape(height, width, 3).copy())
        return pictures


#: The observations an env can give (``obs_mode``): the LiDAR scan; the scan and the episode's
#: context ``(c_v, c_θ)`` in one array; or a Dict of the scan, the context and the race's state
#: (the ego's pose x, y, yaw, its speed and yaw rate; each rival's position and heading relative
#: to the ego in its frame, and its speed), as f1tenth_gym returns it beside the scan.
OBS_MODES = ("scan", "scan+context", "dict")


def observation_space(mode: str, beams: int, state_bounds: tuple) -> spaces.Space:
    """One env's observation space in `mode` (see `OBS_MODES`); the state's bounds `(low,
    high)` are the simulator's."""
    scan = spaces.Box(0.0, 1.0, (beams,), np.float32)
    context = spaces.Box(-CONTEXT_LIMIT, CONTEXT_LIMIT, (2,), np.float32)
    if mode == "scan":
        return scan
    if mode == "scan+context":
        low = np.concatenate([scan.low, context.low]).astype(np.float32)
        high = np.concatenate([scan.high, context.high]).astype(np.float32)
        return spaces.Box(low, high, dtype=np.float32)
    low, high = (np.asarray(b, dtype=np.float32) for b in state_bounds)
    state = spaces.Box(low, high, dtype=np.float32)
    return spaces.Dict({"scan": scan, "context": context, "state": state})


def rows(obs, ended: np.ndarray):
    """The rows `ended` of observations (an array or a dict of arrays), the others zero."""
    if isinstance(obs, dict):
        return {k: rows(v, ended) for k, v in obs.items()}
    out = np.zeros_like(obs)
    out[ended] = obs[ended]
    return out


def first(obs):
    """The first env's observation (an array or a dict of arrays)."""
    if isinstance(obs, dict):
        return {k: v[0] for k, v in obs.items()}
    return obs[0]


def info_of(table: np.ndarray) -> dict:
    """The info arrays of an outcome table: context, progress, overtakes, a2a, wall_crash."""
    return {
        # the two adjacent columns as a slice (fancy indexing costs more per step)
        "context": table[:, _COLUMNS["context_speed"] : _COLUMNS["context_steer"] + 1].copy(),
        "progress": table[:, _COLUMNS["progress"]].copy(),
        "overtakes": table[:, _COLUMNS["overtakes"]].astype(np.int64),
        "a2a": table[:, _COLUMNS["a2a"]] != 0,
        "wall_crash": table[:, _COLUMNS["wall_crash"]] != 0,
    }


def _seed_of(seed: Optional[int], rng: np.random.Generator) -> int:
    """The simulator's reset seed: `seed`, else one drawn from the env's generator."""
    if seed is None:
        return int(rng.integers(2**63))
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise TypeError(f"seed must be a non-negative int or None, not {seed!r}")
    return int(seed)


class RaceVectorEnv(PicklesAsMade, VectorEnv):
    """`num_envs` head-to-head races of one track and scenario, stepped together in Rust on
    worker threads with the GIL released.

    Observations: the ego's LiDAR, ``(num_envs, beams)`` float32 in [0, 1]. Actions:
    ``(num_envs, 2)`` floats in [-1, 1] (steering, speed). Autoreset as Gymnasium's
    ``AutoresetMode.NEXT_STEP`` (default): the step after an env's episode ended resets it
    (reward 0, its action ignored); or, with ``autoreset_mode=AutoresetMode.SAME_STEP`` (as
    Stable-Baselines3's vector envs work), in the step that ended it: that step returns the new
    episode's first observation and reset info, the ended episode's last observation in
    ``info["final_obs"]`` and its step info in ``info["final_info"]`` (masks ``_final_obs``,
    ``_final_info``). Each episode's context is drawn from ``±context_range`` unless
    ``reset(options={"context": (num_envs, 2) array})`` pins it (for that env's later episodes
    too, until a reset without one). ``reset(seed=S)`` starts env ``i`` from the simulator's
    reset seed ``S + i``, as ``ctxrace race --seed S + i`` does. Info arrays: ``context``,
    ``progress``, ``overtakes`` (this step's rank change), ``a2a``, ``wall_crash``.
    ``render_mode="rgb_array"``: ``render()`` draws every env's race as `RaceEnv.render` does.

    Multi-agent (``agents`` > 1, as `make_agents_vec` makes it): each of the `num_envs` races
    drives `agents` cars from Python (``car_0``, the ego, and the cars ahead of it on the grid,
    on top of the `rivals` scripted ones) and the vector's envs are their agents, race-major:
    ``self.num_envs`` is races x agents and env ``r * agents + i`` is ``car_i`` of race ``r``.
    An agent that crashed before its race ended reports a zero observation, reward 0 and no
    flag (SuperSuit's black death) until the race ends, when each of its agents' envs reports
    terminated or truncated; the next step (or, under ``SAME_STEP``, that step) starts all of
    them again. Contexts and ``reset(options={"context": ...})`` are per race (one row a race).
    """

    #: Frames a second at the default scenario's decision period; an env's own ``metadata``
    #: has its scenario's.
    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, **render_metadata(_ctxrace.DEFAULT_RENDER_FPS)}

    def __init__(
        self,
        track: str = "generated:0",
        num_envs: int = 1,
        rivals: int = 1,
        seed: Optional[int] = None,
        tracks_dir: Optional[os.PathLike] = None,
        config: Optional[os.PathLike] = None,
        context_range: float = _ctxrace.TRAIN_CONTEXT_RANGE,
        threads: int = 0,
        autoreset_mode: AutoresetMode = AutoresetMode.NEXT_STEP,
        render_mode: Optional[str] = None,
        obs_mode: str = "scan",
        agents: int = 1,
        **race_keys: Any,
    ):
        self.remember(locals(), ("track", "num_envs"))
        modes = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)
        if autoreset_mode not in modes:
            raise ValueError(
                f"autoreset_mode {autoreset_mode!r}: ctxrace's vector env takes "
                "AutoresetMode.NEXT_STEP or AutoresetMode.SAME_STEP"
            )
        self._same_step = autoreset_mode == AutoresetMode.SAME_STEP
        self.metadata = {**self.metadata, "autoreset_mode": autoreset_mode}
        self._races = Races(
            track,
            num_envs,
            rivals,
            tracks_dir,
            config,
            context_range,
            threads,
            race_keys,
            self._same_step,
            render_mode,
            obs_mode,
            agents,
        )
        self.render_mode = render_mode
        self.metadata = {**self.metadata, **self._races.metadata}
        num_envs = self._races.num_envs
        self.num_envs = num_envs
        self.race_config = self._races.race_config
        self.single_observation_space = self._races.single_observation_space
        self.single_action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._first_seed = seed
        if seed is not None:
            self.action_space.seed(seed)

    @property
    def threads(self) -> int:
        """Worker threads stepping the envs."""
        return self._live().inner.threads

    def _live(self) -> Races:
        """The races, unless the env was closed."""
        if self.closed:
            raise ClosedEnvironmentError("the env is closed; make a new one")
        return self._races

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Starts every env's next episode; ``options={"context": (races, 2)}`` pins contexts."""
        races = self._live()
        if seed is None and self._first_seed is not None:
            seed, self._first_seed = self._first_seed, None
        super().reset(seed=seed)
        contexts = (options or {}).get("context")
        obs, table = races.reset(_seed_of(seed, self.np_random), contexts)
        return obs, info_of(table)

    def step(self, actions):
        """Steps every env with its action; returns (obs, reward, terminated, truncated, info)."""
        races = self._live()
        obs, table = races.step(actions)
        terminated = table[:, _COLUMNS["terminated"]] != 0
        truncated = table[:, _COLUMNS["truncated"]] != 0
        info = info_of(table)
        ended = terminated | truncated
        if self._same_step and ended.any():
            info = _restarted(races, info, ended)
        return obs, table[:, _COLUMNS["reward"]].copy(), terminated, truncated, info

    def render(self) -> Optional[tuple]:
        """Every env's race so far (``render_mode="rgb_array"``; None without a mode): a tuple
        of ``(height, 1000, 3)`` uint8 arrays, env by env, drawn as `RaceEnv.render` draws."""
        pictures = self._live().render()
        return None if pictures is None else tuple(pictures)

    def get_attr(self, name: str) -> tuple:
        """Each env's attribute `name`, a tuple of one value per env as Gymnasium's
        ``SyncVectorEnv.get_attr`` gives it: ``context`` per env; ``observation_space`` and
        ``action_space`` a single env's; any other attribute of this env (``race_config``,
        ``render_mode``, ``metadata``, ...) shared by every env."""
        races = self._live()
        if name == "context":
            return tuple(races.contexts())
        single = {
            "observation_space": self.single_observation_space,
            "action_space": self.single_action_space,
        }
        value = single[name] if name in single else getattr(self, name)
        return (value,) * self.num_envs

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Gymnasium's ``SyncVectorEnv.call``, a tuple of one result per env: ``render`` draws
        each env's race; an attribute that is no method is `get_attr`'s. The races step
        together in Rust, so no other method can be called env by env."""
        if name == "render":
            return self.render() or (None,) * self.num_envs
        values = self.get_attr(name)
        if callable(values[0]):
            raise AttributeError(
                f"{name!r}: ctxrace's vector env steps its races together in Rust and calls "
                "only 'render' env by env; read attributes with get_attr"
            )
        return values

    def close_extras(self, **kwargs: Any):
        """Frees the races."""
        self._races = None


def _restarted(races: Races, info: dict, ended: np.ndarray) -> dict:
    """Gymnasium's same-step info after the envs `ended` started new episodes: their new
    episodes' reset info (context, zero progress) at the top level, the ended step's info under
    ``final_info`` and the ended episodes' last observations under ``final_obs``."""
    final_obs = rows(races.final_obs(info["context"]), ended)
    final_info = {key: value.copy() for key, value in info.items()}
    final_info.update({f"_{key}": ended for key in info})
    info["context"][ended] = races.contexts()[ended]
    for key in ("progress", "overtakes", "a2a", "wall_crash"):
        info[key][ended] = 0
    info.update(final_obs=final_obs, _final_obs=ended, final_info=final_info, _final_info=ended)
    return info


class RaceEnv(PicklesAsMade, gymnasium.Env):
    """One head-to-head race (``gymnasium.make("ctxrace/Race-v0", track=..., rivals=...)``):
    the spaces, contexts and seeds of `RaceVectorEnv` for a single env; ``reset(options={"context":
    (c_v, c_θ)})`` pins the context; ``step`` after the episode ended raises ``ResetNeeded``."""

    #: Frames a second at the default scenario's decision period (0.1 s); an env's own
    #: ``metadata`` has its scenario's.
    metadata = render_metadata(_ctxrace.DEFAULT_RENDER_FPS)

    def __init__(
        self,
        track: str = "generated:0",
        rivals: int = 1,
        tracks_dir: Optional[os.PathLike] = None,
        config: Optional[os.PathLike] = None,
        context_range: float = _ctxrace.TRAIN_CONTEXT_RANGE,
        render_mode: Optional[str] = None,
        obs_mode: str = "scan",
        **race_keys: Any,
    ):
        self.remember(locals(), ("track",))
        self._races = Races(
            track,
            1,
            rivals,
            tracks_dir,
            config,
            context_range,
            1,
            race_keys,
            False,
            render_mode,
            obs_mode,
        )
        self.race_config = self._races.race_config
        self.observation_space = self._races.single_observation_space
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.render_mode = render_mode
        self.metadata = self._races.metadata
        self._ended = True

    def _live(self) -> Races:
        """The race, unless the env was closed."""
        if self._races is None:
            raise ClosedEnvironmentError("the env is closed; make a new one")
        return self._races

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Starts an episode; ``options={"context": (c_v, c_θ)}`` pins the context."""
        races = self._live()
        super().reset(seed=seed)
        context = (options or {}).get("context")
        if context is not None:
            context = np.asarray(context).reshape(1, -1)
        obs, table = races.reset(_seed_of(seed, self.np_random), context)
        self._ended = False
        return first(obs), _single(info_of(table))

    def step(self, action):
        """One decision: returns (obs, reward, terminated, truncated, info)."""
        races = self._live()
        if self._ended:
            raise ResetNeeded("the episode has ended (or never started): call reset")
        a = np.asarray(action)
        obs, table = races.step(a.reshape(1, -1) if a.ndim == 1 else a)
        row = table[0]
        terminated = bool(row[_COLUMNS["terminated"]])
        truncated = bool(row[_COLUMNS["truncated"]])
        self._ended = terminated or truncated
        return first(obs), float(row[_COLUMNS["reward"]]), terminated, truncated, _single(
            info_of(table)
        )

    def render(self) -> Optional[np.ndarray]:
        """The race so far as ``ctxrace race --render race.gif`` draws its moments, an
        ``(height, 1000, 3)`` uint8 array (``render_mode="rgb_array"``; None without a mode):
        the track, each car filled at its place trailing its last 3 s of path coloured by
        speed, the title with the context, the progress and the race time."""
        pictures = self._live().render()
        return None if pictures is None else pictures[0]

    def close(self):
        """Frees the race."""
        self._races = None


def _single(info: dict) -> dict:
    """The first env's entries of vector info arrays."""
    out = {k: v[0] for k, v in info.items()}
    out["context"] = info["context"][0]
    return out


def make_vec(
    track: str,
    num_envs: int,
    rivals: int = 1,
    seed: Optional[int] = None,
    tracks_dir: Optional[os.PathLike] = None,
    **kwargs: Any,
) -> RaceVectorEnv:
    """`num_envs` races on `track` (a name in `tracks_dir` / ``$CTXRACE_TRACKS_DIR`` / the
    per-user folder, a map yaml, or ``generated:SEED``) against `rivals` rivals, as a Gymnasium
    vector env; `seed` seeds its first reset. Further keywords: ``config`` (a race config TOML),
    ``context_range`` (0.15), ``threads`` (0: one per core), ``autoreset_mode``
    (``AutoresetMode.NEXT_STEP``, or ``SAME_STEP`` as Stable-Baselines3 expects), ``render_mode``
    and race keys as the TOML configs name them (``preset="paper-code"``,
    ``rival={"driver": "follow-the-gap"}``, ...)."""
    return RaceVectorEnv(track, num_envs, rivals, seed, tracks_dir, **kwargs)


def make_agents_vec(
    track: str,
    races: int,
    agents: int = 2,
    rivals: int = 1,
    seed: Optional[int] = None,
    tracks_dir: Optional[os.PathLike] = None,
    **kwargs: Any,
) -> RaceVectorEnv:
    """`races` multi-agent races on `track`, `agents` cars of each driven from Python beside
    `rivals` scripted rivals, as one Gymnasium vector env of ``races x agents`` envs (see
    `RaceVectorEnv`'s multi-agent form): `parallel_env` vectorised in Rust, for self-play and
    populations. Keywords as `make_vec`'s."""
    return RaceVectorEnv(track, races, rivals, seed, tracks_dir, agents=agents, **kwargs)
