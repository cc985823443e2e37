"""Env steps/s of `ctxrace.make_vec` with random actions at num_envs 1, 16 and 64 against 1 and
3 rivals, on 1 thread and on every core, side by side with the Rust-only stepping of one core
(`ctxrace bench sim --ego random`) in the same run.

With --agents, also multi-agent races (16 races of 2 agents and 1 scripted rival: 32 agent
envs): `ctxrace.make_agents_vec` on 1 thread and every core against SuperSuit's vectorised
`parallel_env` (black_death_v3, pettingzoo_env_to_vec_env_v1, concat_vec_envs_v1; needs
supersuit), in agent steps/s.

With --paper-python and --paper-work, also the paper's simulator (lilpharaoh1/context-f110 at
c0fd903, its f1tenth_gym copy) racing the same race with random ego actions, measured by
deploy/paper_sim_rate.py in the paper's own Python environment (deploy/paper_sim_agreement.sh
setup; --paper-work: its export of the commit, PAPER_WORK) between the other measurements of
each rivals count. It is one env on one core (the paper's simulator is not vectorised), so each
num_envs row shows the same value; "1 thr/paper" is ctxrace's 1-thread column over it.

    python deploy/python/bench.py [--track f1_esp] [--seconds 3] [--tracks-dir DIR] [--bin PATH]
        [--paper-python /work/venv-sim/bin/python --paper-work /work/sim-paper]
"""

import argparse
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np

import ctxrace

ROOT = Path(__file__).resolve().parents[2]


def python_rate(track, num_envs, rivals, threads, seconds, tracks_dir):
    """Env steps/s of a vector env stepped with uniform random actions for `seconds`."""
    env = ctxrace.make_vec(track, num_envs, rivals=rivals, threads=threads, tracks_dir=tracks_dir)
    return rate(env, seconds)


def rate(env, seconds):
    """Env steps/s of the Gymnasium vector env `env` stepped with uniform random actions for
    `seconds`, then closed."""
    num_envs = env.num_envs
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(64, num_envs, 2))
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for a in actions:
            env.step(a)
        steps += len(actions)
    per_s = steps * num_envs / (time.perf_counter() - start)
    env.close()
    return per_s


def rust_rate(binary, track, rivals, seconds, tracks_dir):
    """Decisions/s of `ctxrace bench sim` with the random ego (one core)."""
    out = subprocess.run(
        [binary, "bench", "sim", track, "--rivals", str(rivals), "--ego", "random",
         "--seconds", str(seconds), "--json", "--tracks-dir", str(tracks_dir)],
        check=True, capture_output=True, text=True,
    ).stdout
    return json.loads(out)["decisions_per_s"]


def paper_rate(python, work, rivals, seconds):
    """Decisions/s (env steps/s, one env) of the paper's simulator with the random ego, from
    deploy/paper_sim_rate.py run by the paper environment's `python` in the export `work`."""
    proc = subprocess.run(
        [python, str(ROOT / "deploy" / "paper_sim_rate.py"), str(Path(work).resolve()),
         "--rivals", str(rivals), "--seconds", str(seconds)],
        capture_output=True, text=True,
    )
    if proc.returncode != 0:
        raise SystemExit(f"paper_sim_rate.py failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.splitlines()[-1])["decisions_per_s"]


def agents_rates(track, seconds, tracks_dir, races=16, agents=2, rivals=1):
    """Agent steps/s of `races` multi-agent races: make_agents_vec on 1 thread and every core,
    and SuperSuit's vectorised parallel_env."""
    import supersuit as ss

    keys = dict(agents=agents, rivals=rivals, tracks_dir=tracks_dir)
    rust = [rate(ctxrace.make_agents_vec(track, races, threads=t, **keys), seconds)
            for t in (1, 0)]
    env = ss.pettingzoo_env_to_vec_env_v1(ss.black_death_v3(ctxrace.parallel_env(track, **keys)))
    supersuit = rate(ss.concat_vec_envs_v1(env, races, num_cpus=0, base_class="gymnasium"),
                     seconds)
    return rust, supersuit


def main():
    """Measures every cell and prints the table, one row as soon as it is measured."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--track", default="f1_esp")
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--tracks-dir", default=os.environ.get(
        "CTXRACE_TRACKS_DIR", str(ROOT.parent / "shared" / "tracks")))
    p.add_argument("--bin", default=os.environ.get(
        "CTXRACE_BIN", str(ROOT / "target" / "release" / "ctxrace")))
    p.add_argument("--agents", action="store_true",
                   help="also multi-agent races: make_agents_vec against SuperSuit")
    p.add_argument("--paper-python", help="Python of the paper simulator's environment")
    p.add_argument("--paper-work", help="export of the paper's code at c0fd903 (PAPER_WORK)")
    args = p.parse_args()
    paper = args.paper_python is not None
    if paper != (args.paper_work is not None):
        p.error("--paper-python and --paper-work go together")
    cores = os.cpu_count()
    print(f"{args.track}, random actions, {args.seconds:g} s per cell, {cores} cores")
    print(f"{'rivals':>6} {'envs':>5} {'1 thread':>10} {'of Rust':>8} "
          f"{f'{cores} threads':>11} {'per core':>9} {'Rust 1 core':>12}"
          + (f" {'paper':>7} {'1 thr/paper':>12}" if paper else ""), flush=True)
    for rivals in (1, 3):
        rust = rust_rate(args.bin, args.track, rivals, args.seconds, args.tracks_dir)
        if paper:
            slow = paper_rate(args.paper_python, args.paper_work, rivals, args.seconds)
        for num_envs in (1, 16, 64):
            one = python_rate(args.track, num_envs, rivals, 1, args.seconds, args.tracks_dir)
            every = python_rate(args.track, num_envs, rivals, 0, args.seconds, args.tracks_dir)
            print(f"{rivals:>6} {num_envs:>5} {one:>10.0f} {one / rust:>8.2f} "
                  f"{every:>11.0f} {every / cores / rust:>9.2f} {rust:>12.0f}"
                  + (f" {slow:>7.0f} {one / slow:>12.0f}" if paper else ""), flush=True)
    if args.agents:
        (one, every), supersuit = agents_rates(args.track, args.seconds, args.tracks_dir)
        print(f"16 races x 2 agents, 1 rival (agent steps/s): make_agents_vec {one:.0f} on 1 "
              f"thread, {every:.0f} on {cores}; SuperSuit {supersuit:.0f} "
              f"({one / supersuit:.1f}x on 1 thread)", flush=True)


if __name__ == "__main__":
    main()
