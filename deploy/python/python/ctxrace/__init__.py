"""ctxrace from Python: contextual head-to-head F1TENTH races on ctxrace's Rust simulator as
Gymnasium envs (``gymnasium.make("ctxrace/Race-v0", ...)``, ``gymnasium.make_vec(
"ctxrace/Race-v0", num_envs=N, ...)`` or `make_vec`), and the paper's
evaluation protocol for any policy (`evaluate`); one race of any policy, drawn (`race`);
trained agents' policies (`load_policy`), their ONNX models (`export_onnx`) and Python's for the
command line (`save_mlp_policy`); multi-agent races as a PettingZoo ``ParallelEnv``
(`parallel_env`) and vectorised in Rust (`make_agents_vec`); tracks (`ctxrace.tracks.list`, `ctxrace.tracks.download`); the vector env as
Stable-Baselines3's ``VecEnv`` with episode statistics (`ctxrace.sb3.VecEnv`, imported on its
own: ``import ctxrace.sb3`` needs SB3, ``import ctxrace`` does not)."""

import gymnasium

from ctxrace import tracks
from ctxrace._agents import RaceParallelEnv, parallel_env
from ctxrace._ctxrace import __version__
from ctxrace._env import OBS_MODES, RaceEnv, RaceVectorEnv, make_agents_vec, make_vec
from ctxrace._evaluate import REFERENCE_POLICIES, Evaluation, evaluate
from ctxrace._policy import TrainedPolicy, export_onnx, load_policy, save_mlp_policy
from ctxrace._race import race

__all__ = [
    "__version__",
    "RaceEnv",
    "RaceVectorEnv",
    "make_vec",
    "make_agents_vec",
    "OBS_MODES",
    "evaluate",
    "Evaluation",
    "REFERENCE_POLICIES",
    "load_policy",
    "TrainedPolicy",
    "save_mlp_policy",
    "export_onnx",
    "race",
    "parallel_env",
    "RaceParallelEnv",
    "tracks",
]

if "ctxrace/Race-v0" not in gymnasium.registry:
    # gymnasium.make_vec("ctxrace/Race-v0", num_envs=N, ...) builds ctxrace's own vector env,
    # stepped in Rust, by default (vectorization_mode="vector_entry_point")
    gymnasium.register(
        id="ctxrace/Race-v0",
        entry_point="ctxrace._env:RaceEnv",
        vector_entry_point="ctxrace._env:RaceVectorEnv",
    )
