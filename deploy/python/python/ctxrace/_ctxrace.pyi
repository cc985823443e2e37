"""Type stubs of the extension module `ctxrace._ctxrace` (Rust, deploy/python/src): races
stepped in Rust, the evaluation protocol, trained agents' policies and their ONNX models, and
tracks. Arrays cross as native-endian bytes (`f32` observations and states, `f64` pairs for
actions and contexts) that the package views with numpy; `tests/test_stubs.py` holds this file
to the module."""

from os import PathLike
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple, Union

_Path = Union[str, PathLike]

__version__: str
#: Largest magnitude of a context element the simulator takes.
CONTEXT_LIMIT: float
MLP_ACTIVATIONS: List[str]
MLP_INPUTS: List[str]
MLP_OUTPUTS: List[str]
#: Frames a second of a render at the default race's decision period.
DEFAULT_RENDER_FPS: float
#: The evaluation protocol's grid points per context dimension, half-width and laps per context.
EVAL_GRID: int
EVAL_RANGE: float
EVAL_LAPS: int
#: The default training context range (half-width).
TRAIN_CONTEXT_RANGE: float
#: The columns of a vector's outcome table, in order.
OUTCOME_COLUMNS: List[str]
#: The reference policies the simulator drives itself.
REFERENCE_POLICIES: List[str]

class RaceVector:
    """`num_envs` races stepped in Rust on worker threads, `agents` cars of each driven from
    Python (its rows: races x agents, race-major)."""

    def __init__(
        self,
        track: str,
        num_envs: int,
        race_keys: str = "{}",
        config: Optional[_Path] = None,
        tracks_dir: Optional[_Path] = None,
        context_range: float = 0.15,
        threads: int = 0,
        same_step: bool = False,
        record: bool = False,
        agents: int = 1,
    ) -> None: ...
    @property
    def num_envs(self) -> int: ...
    @property
    def races(self) -> int: ...
    @property
    def agents(self) -> int: ...
    @property
    def obs_dim(self) -> int: ...
    @property
    def threads(self) -> int: ...
    @property
    def race_config(self) -> str: ...
    @property
    def track(self) -> str: ...
    @property
    def state_dim(self) -> int: ...
    @property
    def state_bounds(self) -> Tuple[List[float], List[float]]: ...
    @property
    def decision_period(self) -> float: ...
    def final_obs(self) -> bytes: ...
    def states(self, ended: bool = False) -> bytes: ...
    def contexts(self) -> bytes: ...
    def render(self, env: int, width: int = ...) -> Tuple[bytes, int, int]: ...
    def metrics(self, env: int) -> str: ...
    def save_render(self, env: int, path: _Path, ego: str) -> None: ...
    def reset(self, seed: int, contexts: Optional[bytes] = None) -> Tuple[bytes, bytes]: ...
    def step(self, actions: bytes) -> Tuple[bytes, bytes]: ...

class RaceAgents:
    """One race of several agents driven from Python and its scripted rivals."""

    def __init__(
        self,
        track: str,
        agents: int,
        race_keys: str = "{}",
        config: Optional[_Path] = None,
        tracks_dir: Optional[_Path] = None,
        context_range: float = 0.15,
        record: bool = False,
    ) -> None: ...
    @property
    def agents(self) -> int: ...
    @property
    def obs_dim(self) -> int: ...
    @property
    def race_config(self) -> str: ...
    @property
    def track(self) -> str: ...
    @property
    def state_dim(self) -> int: ...
    @property
    def state_bounds(self) -> Tuple[List[float], List[float]]: ...
    @property
    def decision_period(self) -> float: ...
    @property
    def finished(self) -> bool: ...
    @property
    def context(self) -> Tuple[float, float]: ...
    def states(self) -> bytes: ...
    def render(self, width: int = ...) -> Tuple[bytes, int, int]: ...
    def reset(
        self, seed: int, context: Optional[Tuple[float, float]] = None
    ) -> Tuple[bytes, bytes]: ...
    def step(self, actions: bytes) -> Tuple[bytes, bytes]: ...

class Evaluation:
    """The evaluation protocol driven by a Python policy, `batch` episodes at a time."""

    def __init__(
        self,
        track: Optional[str] = None,
        rivals: Optional[int] = None,
        train_range: Optional[float] = None,
        race_keys: str = "{}",
        config: Optional[_Path] = None,
        tracks_dir: Optional[_Path] = None,
        run: Optional[Policy] = None,
        grid: int = ...,
        range: float = ...,
        laps: int = ...,
        seed: int = 0,
        batch: int = 64,
        threads: int = 0,
    ) -> None: ...
    @property
    def racing_now(self) -> int: ...
    @property
    def obs_dim(self) -> int: ...
    def lanes(self) -> List[int]: ...
    def started(self) -> List[Tuple[int, int]]: ...
    def observe(self) -> Tuple[bytes, bytes]: ...
    def act(self, actions: bytes) -> None: ...
    def result(self) -> str: ...

class Policy:
    """A trained agent's acting policy over a batch of episodes."""

    def __init__(self, path: _Path, checkpoint: Optional[str] = None) -> None: ...
    @property
    def algo(self) -> str: ...
    @property
    def checkpoint(self) -> Path: ...
    @property
    def obs_dim(self) -> int: ...
    @property
    def race_config(self) -> str: ...
    @property
    def track(self) -> Optional[str]: ...
    @property
    def context_range(self) -> Optional[float]: ...
    def reset(
        self, rows: Optional[List[int]] = None, seeds: Optional[List[int]] = None
    ) -> None: ...
    def act(
        self,
        obs: bytes,
        contexts: bytes,
        deterministic: bool = False,
        rows: Optional[List[int]] = None,
    ) -> Tuple[bytes, Optional[bytes]]: ...

def evaluate_reference(
    policy: str,
    track: Optional[str] = None,
    rivals: Optional[int] = None,
    train_range: Optional[float] = None,
    race_keys: str = "{}",
    config: Optional[_Path] = None,
    tracks_dir: Optional[_Path] = None,
    grid: int = ...,
    range: float = ...,
    laps: int = ...,
    seed: int = 0,
    threads: int = 0,
) -> str: ...
def save_mlp_policy(
    path: str,
    layers: List[Tuple[bytes, int, int, bytes]],
    activation: Optional[str] = None,
    inputs: Optional[str] = None,
    output: Optional[str] = None,
    obs_dim: Optional[int] = None,
) -> None: ...
def export_onnx(
    path: _Path, out: _Path, checkpoint: Optional[str] = None
) -> Dict[str, Any]: ...
def list_tracks(tracks_dir: Optional[_Path] = None) -> List[Tuple[str, Path]]: ...
def download_track(
    name: str, source: Optional[str] = None, into: Optional[_Path] = None
) -> Path: ...
