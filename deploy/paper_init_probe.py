"""The paper's own DreamerV3 (c0fd903, torch on CPU) trained for a few hundred gradient steps on
a paper run's replay, from its own initialisation or from ctxrace's, everything else equal: how
much of the speed of early learning the initial weights decide (docs/parity/one_batch.md).

    deploy/paper_parity.sh export DIR        (WIDTH=64 STOCH=8 LENGTH=32 AC_LR=0.0001: parity.toml)
    /work/venv-paper/bin/python deploy/paper_init_probe.py DIR BUFFER --init paper|ctxrace \
        [--steps 300] [--seed 0] [--model-lr 3e-4] > probe-INIT-SEED.csv
    /work/venv-paper/bin/python deploy/paper_init_probe.py --table probe-*.csv

The replay grows as in training: the run's first 32 episodes, then one row of its later
episodes per gradient step (the code's `train()` draws each batch with a fresh RandomState(0)).
`--init ctxrace` replaces every linear layer's weights by ctxrace's `ParamStore::init` draw
(uniform in ±1/sqrt(fan_in)), biases zero, the reward head's and the critic's output layers at
zero as ctxrace starts them; `paper` keeps the code's (truncated normal of variance 1/fan_avg,
output layers uniform of variance outscale/fan_avg). Writes one CSV row per gradient step of
the code's own metrics; `--table` prints the means per 50 steps of such files as a Markdown
table (the init and seed read from the names `probe-INIT-SEED.csv`).
"""
import argparse
import contextlib
import glob
import os
import sys

import numpy as np

COLUMNS = ["model_loss", "image_loss", "reward_loss", "cont_loss", "kl", "actor_loss",
           "value_loss", "actor_entropy", "imag_reward_mean", "target_mean", "value_mean",
           "imag_action_std", "model_grad_norm", "actor_grad_norm"]


def episodes_of(folder):
    paths = sorted(glob.glob(f"{folder}/eps_*-*.npz"),
                   key=lambda p: int(os.path.basename(p)[4:].split("-")[0]))
    if len(paths) < 33:
        sys.exit(f"{folder}: fewer than 33 episodes (a paper run's Buffer/ folder?)")
    out = []
    for p in paths:
        with np.load(p) as d:
            out.append({k: d[k] for k in d.files})
    return out


def ctxrace_init(agent, torch):
    """ctxrace's initial weights in the code's modules: every Linear's weight uniform in
    ±1/sqrt(fan_in), biases zero; the reward and critic output layers zero."""
    for m in agent.modules():
        if isinstance(m, torch.nn.Linear):
            bound = 1.0 / np.sqrt(m.in_features)
            torch.nn.init.uniform_(m.weight, -bound, bound)
            if m.bias is not None:
                torch.nn.init.zeros_(m.bias)
    beh = agent._task_behavior
    for layer in (agent._wm.heads["reward"].mean_layer, beh.value.mean_layer):
        torch.nn.init.zeros_(layer.weight)
    beh._slow_value.load_state_dict(beh.value.state_dict())


TABLE = [("model_loss", "model loss"), ("image_loss", "reconstruction"), ("reward_loss", "reward"),
         ("cont_loss", "continue"), ("kl", "KL"), ("actor_entropy", "actor entropy"),
         ("target_mean", "λ-return")]


def table(paths, window=50):
    """The means per `window` steps of probe files, one row per file and window."""
    import csv
    print("| init | seed | steps | " + " | ".join(title for _, title in TABLE) + " |")
    print("|---|--:|---|" + "--:|" * len(TABLE))
    for path in sorted(paths):
        _, init, seed = os.path.basename(path)[:-4].split("-")
        rows = list(csv.DictReader(open(path)))
        for a in range(0, len(rows), window):
            w = rows[a:a + window]
            means = [np.mean([float(r[c]) for r in w]) for c, _ in TABLE]
            print(f"| {init} | {seed} | {a}-{a + len(w)} | " + " | ".join(f"{m:.3g}" for m in means) + " |")


def main():
    if sys.argv[1:2] == ["--table"]:
        table(sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export")
    ap.add_argument("buffer")
    ap.add_argument("--init", choices=["paper", "ctxrace"], required=True)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model-lr", type=float, default=3e-4)
    args = ap.parse_args()
    episodes = episodes_of(os.path.abspath(args.buffer))
    os.chdir(args.export)
    sys.path.insert(0, os.path.join(args.export, "TrajectoryAidedLearning/Utils/dreamerv3"))
    import torch
    import dreamerv3

    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    with contextlib.redirect_stdout(sys.stderr):  # the code prints its configuration
        agent = dreamerv3.DreamerV3(108, 2, "probe", lr=args.model_lr)
    with torch.no_grad():
        if args.init == "ctxrace":
            ctxrace_init(agent, torch)
    for k in range(32):
        agent.buffer_eps[f"eps_{k}"] = episodes[k]
    later = iter((k, t) for k in range(32, len(episodes)) for t in range(len(episodes[k]["reward"])))
    print(",".join(["step"] + COLUMNS))
    for step in range(args.steps):
        k, t = next(later)
        name = f"eps_{k}"
        row = {key: v[t:t + 1] for key, v in episodes[k].items()}
        if name not in agent.buffer_eps:
            agent.buffer_eps[name] = row
        else:
            agent.buffer_eps[name] = {key: np.append(agent.buffer_eps[name][key], v, axis=0)
                                      for key, v in row.items()}
        agent.train()
        m = {key: float(np.mean(v[-1])) for key, v in agent._metrics.items()}
        print(",".join([str(step)] + [f"{m.get(c, float('nan')):.6g}" for c in COLUMNS]), flush=True)


if __name__ == "__main__":
    main()
