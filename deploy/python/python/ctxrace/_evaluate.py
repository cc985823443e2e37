"""The paper's evaluation protocol for any policy: `evaluate`."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Callable, Optional, Union

import numpy as np

from ctxrace import _ctxrace
from ctxrace._env import _path, count, pairs_bytes, race_keys_json
from ctxrace._policy import TrainedPolicy

#: The reference policies the simulator drives itself (named in Rust, ``BaselineKind``).
REFERENCE_POLICIES = tuple(_ctxrace.REFERENCE_POLICIES)

#: A batch policy: (observations (k, beams) float32, contexts (k, 2) float64) -> actions (k, 2).
Policy = Callable[[np.ndarray, np.ndarray], Any]


@dataclass
class Evaluation:
    """An evaluation's records: `contexts`, one row per context as ``ctxrace eval`` writes
    ``contexts.json`` (context_speed, context_steer, in_distribution, laps, progress = PG,
    overtakes = OT, a2a = A2A per 50 laps, wall_crash, lap_complete, episode_return), and
    `episodes`, one row per episode as its ``episodes.csv``."""

    contexts: list
    episodes: list
    #: The split means computed in Rust as ``ctxrace eval`` computes them: ``{"in": ..., "out":
    #: ...}``, each ``None`` where the split has no context.
    split_means: dict

    def means(self, in_distribution: bool) -> dict:
        """Mean PG, OT, A2A and wall-crash fraction over the contexts in (or out of) the
        training distribution, as ``ctxrace eval`` prints them (NaN where there are none)."""
        means = self.split_means["in" if in_distribution else "out"]
        if means is None:
            keys = ("progress", "overtakes", "a2a", "wall_crash")
            return {"contexts": 0, **{k: float("nan") for k in keys}}
        return dict(means)


def evaluate(
    policy: Union[str, Policy],
    track: Optional[str] = None,
    rivals: Optional[int] = None,
    grid: int = _ctxrace.EVAL_GRID,
    range: float = _ctxrace.EVAL_RANGE,
    laps: int = _ctxrace.EVAL_LAPS,
    seed: int = 0,
    train_range: Optional[float] = None,
    tracks_dir: Optional[os.PathLike] = None,
    config: Optional[os.PathLike] = None,
    batch: int = 64,
    threads: int = 0,
    deterministic: bool = False,
    **race_keys: Any,
) -> Evaluation:
    """Races every context of the ``grid × grid`` grid over ``±range``, `laps` episodes each,
    from the seeds ``ctxrace eval`` uses, and returns its rows (`Evaluation`).

    `policy` is a reference policy's name (``pure-pursuit``, ``follow-the-gap``, ``random``,
    ``still``: driven in Rust, the rows equal ``ctxrace eval POLICY``'s) or a callable
    ``policy(obs, context) -> actions`` called on `batch` episodes at a time: ``obs`` the
    racing episodes' LiDAR ``(k, beams)``, ``context`` their contexts ``(k, 2)``, returning
    ``(k, 2)`` actions (a stateless policy: the batch's episodes change as they end); or a
    `TrainedPolicy` (`load_policy`), each episode starting afresh with its noise seeded by the
    episode as ``ctxrace eval`` seeds it, sampling unless `deterministic` (``--act mode``).
    `train_range` splits the contexts in and out of distribution; `config`, `tracks_dir` and
    race keys as for `make_vec`.

    Where it races is decided as ``ctxrace eval`` decides it (``ctxrace_sim::scenario`` in
    Rust): a `TrainedPolicy` whose run is known on the run's track against its rivals in its
    race scenario, split by its training context range; otherwise `track`, `rivals` and
    `train_range` default to ``f1_esp``, 3 and 0.15. Arguments given win: `track`, `rivals` and
    `train_range` replace the run's, race keys are laid over its race key by key, and a
    `config` file replaces its race (not its rivals).
    """
    trained = policy if isinstance(policy, TrainedPolicy) else None
    common = dict(
        track=None if track is None else str(track),
        rivals=None if rivals is None else count("rivals", rivals, 0),
        train_range=None if train_range is None else float(train_range),
        race_keys=race_keys_json(None, race_keys),
        config=_path(config),
        tracks_dir=_path(tracks_dir),
        grid=grid,
        range=float(range),
        laps=laps,
        seed=seed,
    )
    if isinstance(policy, str):
        if policy not in REFERENCE_POLICIES:
            raise ValueError(
                f"unknown reference policy {policy!r}: use one of {', '.join(REFERENCE_POLICIES)} "
                "or pass a callable policy(obs, context) -> actions"
            )
        text = _ctxrace.evaluate_reference(policy, **common, threads=threads)
    elif callable(policy) or trained is not None:
        run = _ctxrace.Evaluation(
            **common, run=None if trained is None else trained._inner, batch=batch, threads=threads
        )
        text = _drive(policy, run, deterministic)
    else:
        raise TypeError(
            f"policy must be a reference policy's name or a callable, not {type(policy).__name__}"
        )
    records = json.loads(text)
    return Evaluation(
        contexts=records["contexts"], episodes=records["episodes"], split_means=records["means"]
    )


def _drive(policy: Policy, run: Any, deterministic: bool) -> str:
    """Steps the protocol `run` with `policy` until every episode has ended."""
    dim = run.obs_dim
    while run.racing_now > 0:
        k = run.racing_now
        obs, contexts = run.observe()
        obs = np.frombuffer(obs, dtype=np.float32).reshape(k, dim).copy()
        contexts = np.frombuffer(contexts, dtype=np.float64).reshape(k, 2).copy()
        if isinstance(policy, TrainedPolicy):
            started = run.started()
            if started:
                policy.reset([lane for lane, _ in started], [seed for _, seed in started])
            actions = policy.act(obs, contexts, deterministic, rows=run.lanes())
        else:
            actions = policy(obs, contexts)
        run.act(pairs_bytes("actions", actions, k))
    return run.result()
