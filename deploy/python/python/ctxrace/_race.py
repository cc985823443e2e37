"""One race of any policy, as ``ctxrace race`` drives one, drawn as it draws one: `race`."""

from __future__ import annotations

import json
import os
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np

from ctxrace import _ctxrace
from ctxrace._env import _path, contexts_bytes, count, pairs_bytes, race_keys_json
from ctxrace._policy import TrainedPolicy


def race(
    policy: Union[TrainedPolicy, Callable[[np.ndarray, np.ndarray], Any]],
    track: str = "generated:0",
    rivals: int = 1,
    context: Sequence[float] = (0.0, 0.0),
    seed: int = 0,
    render: Optional[os.PathLike] = None,
    deterministic: bool = False,
    tracks_dir: Optional[os.PathLike] = None,
    config: Optional[os.PathLike] = None,
    name: Optional[str] = None,
    **race_keys: Any,
) -> dict:
    """Races one episode of `policy` against `rivals` rivals driving by `context` and returns
    its metrics as ``ctxrace race --json`` reports them (``progress``, ``overtakes``, ``a2a``,
    ``wall_crash``, ``lap_time``, ``episode_return``, ``steps``, ``ended_by``, ...).

    `policy` is a `TrainedPolicy` (`load_policy`: reset with `seed` and sampling unless
    `deterministic`, so that the race is ``ctxrace race --policy CHECKPOINT --seed SEED``'s) or
    a callable ``policy(obs (1, beams), context (1, 2)) -> action (1, 2)``. `render` draws the
    race as ``ctxrace race --render`` does: a ``.gif`` animation, or the last moment as ``.png``
    or ``.svg``, its title naming the ego `name` (default: the algorithm, or ``python``). Race
    keys, `config` and `tracks_dir` as for `make_vec`."""
    trained = policy if isinstance(policy, TrainedPolicy) else None
    if trained is None and not callable(policy):
        raise TypeError(f"policy must be a TrainedPolicy or a callable, not {type(policy).__name__}")
    races = _ctxrace.RaceVector(
        str(track), 1, race_keys_json(count("rivals", rivals, 0), race_keys), _path(config),
        _path(tracks_dir), record=render is not None,
    )
    pinned = np.asarray(context, dtype=np.float64).reshape(1, 2)
    obs, table = races.reset(count("seed", seed, 0), contexts_bytes(pinned, 1))
    if trained is not None:
        trained.reset([0], [seed])
    columns = _ctxrace.OUTCOME_COLUMNS
    while True:
        o = np.frombuffer(obs, dtype=np.float32).reshape(1, races.obs_dim).copy()
        if trained is not None:
            action = trained.act(o, pinned, deterministic)
        else:
            action = policy(o, pinned.copy())
        obs, table = races.step(pairs_bytes("actions", np.asarray(action).reshape(1, 2), 1))
        outcome = dict(zip(columns, np.frombuffer(table, dtype=np.float64)))
        if outcome["terminated"] or outcome["truncated"]:
            break
    if render is not None:
        ego = name or (trained.algo if trained is not None else "python")
        races.save_render(0, os.fspath(render), ego)
    return json.loads(races.metrics(0))
