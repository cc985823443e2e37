"""Trained agents from Python (`load_policy`) and for use outside ctxrace (`export_onnx`), and
policies trained in Python written for the command line (`save_mlp_policy`)."""

from __future__ import annotations

import json
import os
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np

from ctxrace import _ctxrace
from ctxrace._env import count, pairs_bytes


class TrainedPolicy:
    """A trained agent's acting policy over a batch: row ``i`` of a batch is one episode, with
    its own recurrent state and sampling noise, acting as an actor process acts."""

    def __init__(self, inner: Any):
        self._inner = inner
        #: The algorithm: sac, dreamerv3, crssm or cmask.
        self.algo = inner.algo
        #: The checkpoint folder read.
        self.checkpoint = inner.checkpoint
        #: Values in one observation (LiDAR beams).
        self.obs_dim = inner.obs_dim
        #: The run's race scenario (the default scenario's when the run is unknown).
        self.race_config = json.loads(inner.race_config)
        #: The run's training context range (None when the run is unknown).
        self.context_range = inner.context_range
        #: The run's track (None when the run is unknown).
        self.track = inner.track

    def reset(self, rows: Optional[Sequence[int]] = None, seeds: Optional[Sequence[int]] = None):
        """Starts new episodes in batch `rows` (all when None), restarting their sampling noise
        from `seeds` (one per row) when given: ``ctxrace race --seed S`` resets with ``[S]``."""
        self._inner.reset(
            None if rows is None else [int(r) for r in rows],
            None if seeds is None else [int(s) for s in seeds],
        )

    def act(self, obs: Any, context: Any, deterministic: bool = False,
            rows: Optional[Sequence[int]] = None, return_mask: bool = False
            ) -> Union[np.ndarray, Tuple[np.ndarray, Optional[np.ndarray]]]:
        """Actions for observations ``(k, obs_dim)`` (or one ``(obs_dim,)``) under the episodes'
        contexts ``(k, 2)`` (or one pair): sampled, or the mode if `deterministic`; `rows` names
        the batch rows acting (``0..k`` when None). Returns ``(k, 2)`` (or ``(2,)``) float64;
        with `return_mask`, ``(actions, masks)`` where ``masks`` are cMask's context masks in
        the same shape (None for the other agents)."""
        o = np.asarray(obs)
        if o.dtype.kind != "f":
            raise TypeError(f"obs must be floating-point, not dtype {o.dtype}")
        single = o.ndim == 1
        o = o.reshape(1, -1) if single else o
        if o.ndim != 2 or o.shape[1] != self.obs_dim:
            raise ValueError(f"obs must have shape (k, {self.obs_dim}), not {np.shape(obs)}")
        if not np.isfinite(o).all():
            raise ValueError("obs holds NaN or inf")
        k = len(o)
        c = np.asarray(context)
        c = c.reshape(1, -1) if single else c
        actions, masks = self._inner.act(
            np.ascontiguousarray(o, dtype=np.float32).tobytes(),
            pairs_bytes("context", c, k),
            bool(deterministic),
            None if rows is None else [int(r) for r in rows],
        )

        def pairs(b):
            p = np.frombuffer(b, dtype=np.float64).reshape(k, 2).copy()
            return p[0] if single else p

        if not return_mask:
            return pairs(actions)
        return pairs(actions), None if masks is None else pairs(masks)

    def __call__(self, obs: Any, context: Any) -> np.ndarray:
        """Sampled actions for a batch (`act`)."""
        return self.act(obs, context)


def load_policy(path: os.PathLike, checkpoint: Optional[str] = None) -> TrainedPolicy:
    """The acting policy of a checkpoint folder, or of a run folder's checkpoint `checkpoint`
    (``best``, ``latest``, ``step-N``; default: ``ctxrace eval``'s, ``best``), read and
    verified as ``ctxrace eval`` reads it."""
    return TrainedPolicy(_ctxrace.Policy(os.fspath(path), checkpoint))


def export_onnx(run_or_checkpoint: os.PathLike, path: os.PathLike,
                checkpoint: Optional[str] = None) -> Dict[str, Any]:
    """Writes the ONNX model of a trained agent (a checkpoint folder, or a run folder's
    checkpoint `checkpoint`, as `load_policy` reads it) to `path`, as ``ctxrace export onnx``
    does: one deterministic decision a call, for onnxruntime (e.g. on a car's computer).

    Inputs ``obs`` ``(B, obs_dim)``, ``context`` ``(B, 2)`` (the raw context), ``is_first``
    ``(B,)`` (1 starts an episode as `TrainedPolicy.reset` does; ``state`` is then ignored)
    and ``state`` ``(B, S)``, all float32; outputs ``action`` ``(B, 2)``, ``state_out``
    ``(B, S)`` (pass it as the next call's ``state``) and, for cMask, its context ``mask``
    ``(B, 2)``. Stepped so, its actions are ``load_policy(...).act(obs, context,
    deterministic=True)``'s. The state is DreamerV3's ``[h, z, previous action]`` or SAC's
    previous scans. Returns what was written: ``algo``, ``obs_dim``, ``state_dim``, ``state``
    (its parts as ``(name, start, stop)``), ``outputs``, ``opset`` and ``bytes``. A SAC agent
    whose deterministic action is random (``explore_noise > 0``) or whose frame stack outlives
    an episode (``reset_frame_stack = false``) is refused, as is an MLP policy file."""
    return _ctxrace.export_onnx(os.fspath(run_or_checkpoint), os.fspath(path),
                               None if checkpoint is None else str(checkpoint))


#: The choices of an MLP policy file's metadata (`save_mlp_policy`), the networks' own lists.
MLP_ACTIVATIONS = tuple(_ctxrace.MLP_ACTIVATIONS)
MLP_INPUTS = tuple(_ctxrace.MLP_INPUTS)
MLP_OUTPUTS = tuple(_ctxrace.MLP_OUTPUTS)


def save_mlp_policy(
    path: os.PathLike,
    layers: Sequence[Tuple[Any, Any]],
    activation: Optional[str] = None,
    inputs: Optional[str] = None,
    output: Optional[str] = None,
    obs_dim: Optional[int] = None,
) -> None:
    """Writes a policy trained in Python as an MLP file that the command line races, draws and
    evaluates (``ctxrace race f1_esp --policy policy.safetensors``, ``ctxrace eval
    policy.safetensors``). `layers` are ``(weight (out, in), bias (out,))`` pairs, first to
    last (a torch ``nn.Linear`` gives ``(l.weight.detach().numpy(), l.bias.detach().numpy())``);
    `activation` (`MLP_ACTIVATIONS`, default the first) sits between layers; `inputs` is ``"scan"`` or
    ``"scan+context"`` (the scan then ``(c_v, c_θ)``, as ``obs_mode="scan+context"``); `output`
    ``"clip"`` clips the last layer's two values to ``[-1, 1]``, ``"tanh"`` squashes them. The
    action is ``(steering, speed)`` in ``[-1, 1]``; the file's format is documented in
    ``ctxrace_nn::policy::mlp``."""
    arrays = []
    for i, (weight, bias) in enumerate(layers):
        w = np.ascontiguousarray(weight, dtype=np.float32)
        b = np.ascontiguousarray(bias, dtype=np.float32)
        if w.ndim != 2 or b.shape != (w.shape[0],):
            raise ValueError(
                f"layer {i}: weight must be (out, in) and bias (out,), not {w.shape} and {b.shape}"
            )
        if not (np.isfinite(w).all() and np.isfinite(b).all()):
            raise ValueError(f"layer {i} holds values that are not finite")
        arrays.append((w.tobytes(), w.shape[0], w.shape[1], b.tobytes()))
    _ctxrace.save_mlp_policy(
        os.fspath(path), arrays,
        None if activation is None else str(activation),
        None if inputs is None else str(inputs),
        None if output is None else str(output),
        None if obs_dim is None else count("obs_dim", obs_dim, 1),
    )
