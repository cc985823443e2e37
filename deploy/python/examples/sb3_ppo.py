"""Stable-Baselines3's PPO trained on ctxrace's vector env, evaluated with the paper's protocol.

    pip install torch --index-url https://download.pytorch.org/whl/cpu   # CPU-only: ~3 GB less
    pip install ./deploy/python stable-baselines3
    python deploy/python/examples/sb3_ppo.py --track generated:0 --steps 1000000 --out sb3-run

PPO (SB3's defaults but for the rollout length, the batch and the learning rate, which suit 16
envs) on ``ctxrace.sb3.VecEnv`` (the Rust vector env as SB3's VecEnv) learns from the LiDAR
alone (the context is not shown to it) against one rival whose context is drawn from ±0.15
each episode. Every rollout appends a row to ``<out>/curve.csv``: env steps, wall seconds, the
mean return, progress (PG) and lap fraction of the episodes that ended since the last row (from
their ``info["episode"]``). At the end the trained policy (deterministic actions) and the random
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
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

import ctxrace
import ctxrace.sb3


class Curve(BaseCallback):
    """Appends one row per rollout to `path` (the learning curve) from the statistics of the
    episodes that ended in it (``info["episode"]``, as `ctxrace.sb3.VecEnv` writes them)."""

    def __init__(self, path: Path):
        super().__init__()
        self.file = path.open("w", newline="")
        self.writer = csv.writer(self.file)
        self.writer.writerow(["env_steps", "seconds", "episodes", "return", "progress", "laps"])
        self.ended: list[tuple[float, float, bool]] = []
        self.start = time.monotonic()

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                episode = info["episode"]
                # a lap: the episode ended, neither at the time limit nor in a crash or collision
                lap = not (info["TimeLimit.truncated"] or episode["wall_crash"] or episode["a2a"])
                self.ended.append((episode["r"], episode["progress"], lap))
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

    env = ctxrace.sb3.VecEnv(
        track=args.track, num_envs=args.envs, rivals=args.rivals, tracks_dir=args.tracks_dir
    )
    model = PPO(
        "MlpPolicy",
        env,  # seeded by PPO's seed: env i's first episode from reset seed seed + i
        n_steps=256,
        batch_size=1024,
        learning_rate=3e-4,
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    start = time.monotonic()
    model.learn(args.steps, callback=Curve(args.out / "curve.csv"))
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
