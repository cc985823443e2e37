"""Stable-Baselines3's PPO trained on ctxrace's vector env, evaluated with the paper's protocol.

    pip install ./deploy/python stable-baselines3
    python deploy/python/examples/sb3_ppo.py --track generated:0 --steps 1000000 --out sb3-run

PPO (SB3's defaults but for the rollout length, the batch and the learning rate, which suit 16
envs) learns from the LiDAR alone (the context is not shown to it) against one rival whose
context is drawn from ±0.15 each episode. Every rollout appends a row to ``<out>/curve.csv``:
env steps, wall seconds, the mean return, progress (PG) and lap fraction of the episodes that
ended since the last row. At the end the trained policy (deterministic actions) and the random
policy race the paper's protocol (``ctxrace.evaluate``: a grid of contexts over ±0.3, laps per
context), and ``<out>/evaluation.json`` holds both side by side.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

import ctxrace


class RaceVecEnv(VecEnv):
    """ctxrace's Gymnasium vector env (same-step autoreset) as SB3's `VecEnv`: SB3 resets an
    ended env in the step that ended it and finds the ended episode's last observation in
    ``infos[i]["terminal_observation"]``, which is what SAME_STEP hands back."""

    def __init__(self, env: ctxrace.RaceVectorEnv, seed: int):
        if env.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError("make the env with autoreset_mode=AutoresetMode.SAME_STEP")
        self.env, self._seed, self._actions = env, seed, None
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)

    def reset(self):
        obs, _ = self.env.reset(seed=self._seed)
        self._seed = None
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.env.step(self._actions)
        ended = terminated | truncated
        infos = [{"progress": float(p)} for p in info["progress"]]
        for i in np.flatnonzero(ended):
            final = info["final_info"]
            infos[i] = {
                "terminal_observation": info["final_obs"][i],
                "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                "progress": float(final["progress"][i]),
                "lap": bool(terminated[i] and not final["wall_crash"][i] and not final["a2a"][i]),
            }
        return obs, reward.astype(np.float32), ended, infos

    def close(self) -> None:
        self.env.close()

    def get_attr(self, attr_name, indices=None):
        if attr_name == "render_mode":
            return [None] * self.num_envs
        raise AttributeError(f"RaceVecEnv has no per-env attribute {attr_name!r}")

    def set_attr(self, attr_name, value, indices=None):
        raise AttributeError(f"RaceVecEnv cannot set {attr_name!r}")

    def env_method(self, method_name, *args, indices=None, **kwargs):
        raise AttributeError(f"RaceVecEnv has no per-env method {method_name!r}")

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * self.num_envs


class Curve(BaseCallback):
    """Sums each env's return and appends one row per rollout to `path` (the learning curve)."""

    def __init__(self, path: Path, num_envs: int):
        super().__init__()
        self.file = path.open("w", newline="")
        self.writer = csv.writer(self.file)
        self.writer.writerow(["env_steps", "seconds", "episodes", "return", "progress", "laps"])
        self.returns = np.zeros(num_envs)
        self.ended: list[tuple[float, float, bool]] = []
        self.start = time.monotonic()

    def _on_step(self) -> bool:
        self.returns += self.locals["rewards"]
        for i in np.flatnonzero(self.locals["dones"]):
            info = self.locals["infos"][i]
            self.ended.append((self.returns[i], info["progress"], info["lap"]))
            self.returns[i] = 0.0
        return True

    def _on_rollout_end(self) -> None:
        if not self.ended:
            return
        ret, progress, laps = (np.mean(column) for column in zip(*self.ended))
        seconds = time.monotonic() - self.start
        self.writer.writerow(
            [
                self.num_timesteps,
                f"{seconds:.1f}",
                len(self.ended),
                f"{ret:.3f}",
                f"{progress:.3f}",
                f"{laps:.3f}",
            ]
        )
        self.file.flush()
        print(
            f"{self.num_timesteps:>9} steps {seconds:7.0f} s  return {ret:7.2f}  "
            f"PG {progress:.3f}  laps {laps:.2f}"
        )
        self.ended.clear()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--track", default="generated:0", help="a track name, map yaml or generated:SEED"
    )
    p.add_argument("--rivals", type=int, default=1)
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--steps", type=int, default=1_000_000, help="env steps of training")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--eval-grid", type=int, default=7, help="contexts per axis of the evaluation grid"
    )
    p.add_argument("--eval-laps", type=int, default=10, help="episodes per context")
    p.add_argument("--tracks-dir", default=None)
    p.add_argument("--out", type=Path, default=Path("sb3-run"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)

    env = ctxrace.make_vec(
        args.track,
        args.envs,
        rivals=args.rivals,
        tracks_dir=args.tracks_dir,
        autoreset_mode=AutoresetMode.SAME_STEP,
    )
    model = PPO(
        "MlpPolicy",
        RaceVecEnv(env, args.seed),
        n_steps=256,
        batch_size=1024,
        learning_rate=3e-4,
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    start = time.monotonic()
    model.learn(args.steps, callback=Curve(args.out / "curve.csv", args.envs))
    train_seconds = time.monotonic() - start
    model.save(args.out / "ppo")

    def trained(obs: np.ndarray, context: np.ndarray) -> np.ndarray:
        return model.predict(obs, deterministic=True)[0]

    common = dict(
        track=args.track,
        rivals=args.rivals,
        grid=args.eval_grid,
        laps=args.eval_laps,
        tracks_dir=args.tracks_dir,
    )
    results = {"train_env_steps": args.steps, "train_seconds": round(train_seconds, 1)}
    for name, policy in (("ppo", trained), ("random", "random")):
        evaluation = ctxrace.evaluate(policy, **common)
        results[name] = {
            "in_distribution": evaluation.means(True),
            "out_of_distribution": evaluation.means(False),
        }
        print(name, json.dumps(results[name]))
    (args.out / "evaluation.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
