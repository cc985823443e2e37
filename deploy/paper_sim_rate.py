"""Env steps/s of the paper's simulator (lilpharaoh1/context-f110 at c0fd903, its F110Env copy of
f1tenth_gym) with random ego actions: the race of deploy/paper_sim_agreement.py (f1_esp, RIVALS
PurePursuit rivals, the ego at the back, the code's TestSimulation loop) with its `random` ego,
stepped for SECONDS after WARMUP seconds of stepping (numba compiles on the first steps).

One env step is one decision of the code's loop: the ego's and the rivals' plans, run_step (10
F110Env steps, build_observation with progress, crash, lap and position logic and the code's
state history) and, when a lap ends, the code's end of lap (its history written to Data/) and
reset. The paper's simulator is not vectorised: this is one env on one core. The first test
context (index 17) is raced for the whole measurement (laps per context: 1,000,000).

Run in the paper's Python environment (deploy/paper_sim_agreement.sh setup) with an export of
the commit (PAPER_WORK of that script); writes config/sim_rate.yaml and Data/Vehicles/sim_rate/
there (removed after). Prints one JSON line: decisions_per_s, decisions, seconds, rivals.

Usage: python deploy/paper_sim_rate.py PAPER_DIR [--rivals R] [--seconds S] [--warmup S]
"""
import argparse
import contextlib
import json
import os
import shutil
import sys
import time

from paper_sim_agreement import paper_simulation

NAME = "sim_rate"
LAPS = 1_000_000


class TimeUp(Exception):
    """The measurement's time is over."""


def measure(paper_dir, rivals, seconds, warmup, seed):
    """Decisions/s of the paper's loop with the random ego: a dict for the JSON line."""
    data = os.path.join(os.path.abspath(paper_dir), "Data", "Vehicles", NAME)
    shutil.rmtree(data, ignore_errors=True)
    devnull = open(os.devnull, "w")
    sim, _ = paper_simulation(paper_dir, "random", rivals, LAPS, seed, devnull, NAME)
    clock = {"first": None, "start": None, "decisions": 0, "end": None}
    step = sim.run_step

    def run_step(actions):
        """The harness's run_step, counted; ends the race when the time is up."""
        obs = step(actions)
        now = time.perf_counter()
        if clock["first"] is None:
            clock["first"] = now
        elif clock["start"] is None:
            if now - clock["first"] >= warmup:
                clock["start"] = now
        else:
            clock["decisions"] += 1
            if now - clock["start"] >= seconds:
                clock["end"] = now
                raise TimeUp
        return obs

    sim.run_step = run_step
    try:
        sim.run_testing_evaluation()
    except TimeUp:
        pass
    finally:
        shutil.rmtree(data, ignore_errors=True)
    if clock["end"] is None:
        raise RuntimeError("the paper's run ended before the measurement did")
    elapsed = clock["end"] - clock["start"]
    return {
        "decisions_per_s": clock["decisions"] / elapsed,
        "decisions": clock["decisions"],
        "seconds": elapsed,
        "rivals": rivals,
    }


def main():
    """Measures and prints the JSON line; the paper's own prints go to stderr."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paper_dir")
    ap.add_argument("--rivals", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with contextlib.redirect_stdout(sys.stderr):
        result = measure(args.paper_dir, args.rivals, args.seconds, args.warmup, args.seed)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
