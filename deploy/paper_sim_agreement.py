"""Races a reference ego in the paper's own simulator (lilpharaoh1/context-f110 at c0fd903), run
from an unmodified export of that commit (deploy/paper_sim_agreement.sh paper), and writes one
row per lap.

What is the paper's: its F110Env (f110_gym copy), its TestSimulation.run_testing_evaluation and
run_testing (the 7 x 7 grid, reset_simulation's grid, run_step,
build_observation's crash, progress, lap and overtaking logic, the A2A count), its PurePursuit
rivals (ma_info per context), its StdTrack and reward, its config_file.yaml and run-file keys.
What is the harness's, nothing else:
  - a run file config/<name>.yaml written into the export (the keys of the paper's
    dreamerv3_multiagent_classic_esp.yaml, one run with RIVALS rivals, the ego at the back);
  - the contexts raced (`--contexts`, ctxrace's syntax; the code's own 17-48 by default): the
    module's `enumerate` yields run_testing's grid as these contexts with their grid indices,
    each an int that its `if ma_idx < 17: continue` keeps (`context_loop`);
  - the ego driver (`Ego`), put in place of the trained agent through the module's
    `select_agent` binding: it does what the paper's testers do before acting (below
    v_min_plan = 1 m/s it commands [0, 7]), then drives ctxrace's reference ego of the same
    name: `pure-pursuit` is the paper's own PurePursuit planner at full raceline speed
    (slow_down 1, no context) with ctxrace's ego wheelbase (the car's lf + lr = 0.3302) and the
    ego's steering range 0.4; `random` draws actions uniform in [-1, 1]^2 (its own seeded
    numpy stream per context and lap); `still` the action (0, -1); actions map to commands as
    the paper's FastTransform and ctxrace's paper-code race do (steer -0.4 a0: a positive a0
    turns right; speed
    1 + 2.5 (a1 + 1));
  - torch, cv2 and the learning planners' modules replaced by empty stand-ins before the import
    (TestSimulation imports them; nothing of them runs for these egos), so that the simulator
    needs neither;
  - the recording: each decision's observations (through a wrapper of run_step) and, when
    the code calls the ego's lap_complete at the end of a lap, one row, written at once (an
    interrupted run keeps the laps it finished): c_v, c_theta, lap, progress, overtakes (the
    code's eps_overtakes: the sum of the observations' `overtaking` the ego acted on), a2a
    (`colision_a2a` of the last observation, what the code counts), crash, lap_done, time,
    decisions; and, of the last observation, the ego's `position` (place), how many rivals
    have `colision_done` (rivals_crashed) and the lap's overtakes as
    DataTools/ReviewTesting/redo_overtakes.py recounts them (redo_overtakes): num_agents - 1 -
    the index of the agent in position 1 (its `places[0]`, from the same final progress), so
    0 whenever the rival that started furthest ahead leads.

Usage: python paper_sim_agreement.py PAPER_DIR EGO OUT_CSV [--laps N] [--rivals R] [--seed S]
                                     [--contexts SPEC]
"""
import argparse
import builtins
import csv
import os
import sys
import types

import numpy as np

EGO_WHEELBASE = 0.15875 + 0.17145  # ctxrace's ego pure pursuit: the car's lf + lr
MAX_STEER = 0.4  # the ego's steering range (config_file.yaml max_steer)
MIN_SPEED, MAX_SPEED = 1.0, 6.0  # the ego's speed range (FastTransform, run max_speed)
LAUNCH_BELOW, LAUNCH_SPEED = 1.0, 7.0  # the testers' v_min_plan override


def stub_modules():
    """Empty stand-ins for what TestSimulation imports but these egos never use."""
    torch = types.ModuleType("torch")
    torch.use_deterministic_algorithms = lambda *a, **k: None
    torch.manual_seed = lambda *a, **k: None
    sys.modules["torch"] = torch
    sys.modules["cv2"] = types.ModuleType("cv2")
    for mod, names in {
        "TD3Planners": ["TD3Trainer", "TD3Tester"],
        "SACPlanners": ["SACTrainer", "SACTester"],
        "DreamerV2Planners": ["DreamerV2Trainer", "DreamerV2Tester"],
        "DreamerV3Planners": ["DreamerV3Trainer", "DreamerV3Tester"],
        "cDreamerPlanners": ["cDreamerTrainer", "cDreamerTester"],
        "cbDreamerPlanners": ["cbDreamerTrainer", "cbDreamerTester"],
        "cobDreamerPlanners": ["cobDreamerTrainer", "cobDreamerTester"],
        "cfDreamerPlanners": ["cfDreamerTrainer", "cfDreamerTester"],
    }.items():
        m = types.ModuleType("TrajectoryAidedLearning.Planners." + mod)
        for n in names:
            setattr(m, n, None)
        sys.modules[m.__name__] = m


RUN_FILE = """test_name: "{name}"
architecture: "Harness"
window_in: 2
window_out: 1
map_mode: "Std"
start_n: 0
n: 1
set_n: 1
random_seed: 10000
noise_std: 0.0
start_train_steps: 0
n_train_steps: 0
n_test_laps: {laps}
map_name: "f1_esp"
reward: "Cth"
max_speed: 6
lr: 0.00003
gamma: 0.85
ma_info: [0.15, 0.15, 0.3, 0.3]
runs:
  - adversaries: {adversaries}
    num_agents: {agents}
    target_position: {agents}
"""


def parse_contexts(spec, n=49):
    """The grid indices of a selection in ctxrace's `--contexts` syntax: `skip-first:K`, or a
    comma-separated list of indices and inclusive ranges `a-b`; sorted and distinct."""
    if spec.startswith("skip-first:"):
        chosen = set(range(int(spec.split(":", 1)[1]), n))
    else:
        chosen = set()
        for part in spec.split(","):
            a, _, b = part.partition("-")
            chosen.update(range(int(a), int(b or a) + 1))
    if not chosen or not all(0 <= k < n for k in chosen):
        raise ValueError(f"--contexts {spec!r}: give indices 0 to {n - 1} of the grid")
    return sorted(chosen)


class GridIndex(int):
    """A grid index that the code's `if ma_idx < 17: continue` keeps."""

    def __lt__(self, other):
        return False


def context_loop(contexts):
    """TestSimulation's `enumerate`: run_testing's grid (the one 2-D array the module
    enumerates) as its `contexts` with their grid indices, anything else as the builtin's."""

    def enumerate_(xs, start=0):
        if isinstance(xs, np.ndarray) and xs.ndim == 2:
            return ((GridIndex(k), xs[k]) for k in contexts)
        return builtins.enumerate(xs, start)

    return enumerate_


FIELDS = ["context_speed", "context_steer", "lap", "progress", "overtakes", "a2a", "crash",
          "lap_done", "time", "decisions", "place", "rivals_crashed", "redo_overtakes"]


class Recorder:
    """The rows of the laps raced (each written to `out` as it ends), and the state of the lap
    being raced."""

    def __init__(self, out):
        """Rows go to the open CSV file `out`, its header written now."""
        self.out = csv.DictWriter(out, fieldnames=FIELDS)
        self.out.writeheader()
        self.file = out
        self.rows = []
        self.last = None
        self.context = None
        self.lap = 0
        self.overtakes = 0.0
        self.decisions = 0


class Ego:
    """The harness's ego driver: the code's tester interface (plan, lap_complete)."""

    def __init__(self, kind, run, conf, rec, seed):
        """The ego `kind` of the run `run`, recording into `rec`; `seed` seeds `random`."""
        self.kind, self.rec, self.seed, self.laps = kind, rec, seed, run.n_test_laps
        self.rng = None
        self.pp = None
        if kind == "pure-pursuit":
            from TrajectoryAidedLearning.Planners.PurePursuit import PurePursuit

            self.pp = PurePursuit(run, conf, init=False, ma_info=[0.0, 0.0])
            self.pp.slow_down = 1.0
            self.pp.wheelbase = EGO_WHEELBASE
            self.pp.max_steer = MAX_STEER

    def command(self, action):
        """The command [steer, speed] of an action in [-1, 1]^2."""
        a0, a1 = np.clip(action, -1.0, 1.0)
        return np.array([-a0 * MAX_STEER, MIN_SPEED + (a1 + 1.0) / 2.0 * (MAX_SPEED - MIN_SPEED)])

    def plan(self, obs, context=None):
        """The ego's command for the observation `obs` (the testers' interface)."""
        rec = self.rec
        if rec.decisions == 0:
            rec.context = [float(c) for c in context]
            self.rng = np.random.default_rng([self.seed, len(rec.rows)])
        rec.decisions += 1
        rec.overtakes += obs["overtaking"]
        if obs["state"][3] < LAUNCH_BELOW:
            return np.array([0.0, LAUNCH_SPEED]), None
        if self.kind == "pure-pursuit":
            steer, speed = self.pp.plan(obs)
            steer = float(np.clip(steer, -MAX_STEER, MAX_STEER))
            return np.array([steer, float(np.clip(speed, MIN_SPEED, MAX_SPEED))]), None
        if self.kind == "random":
            return self.command(self.rng.uniform(-1.0, 1.0, size=2)), None
        return self.command([0.0, -1.0]), None

    def lap_complete(self):
        """Writes the lap's row and starts the next lap's state."""
        rec = self.rec
        ego = rec.last[0]
        rec.rows.append(
            row := {
                "context_speed": rec.context[0],
                "context_steer": rec.context[1],
                "lap": rec.lap,
                "progress": float(ego["progress"]),
                "overtakes": float(rec.overtakes),
                "a2a": int(bool(ego["colision_a2a"])),
                "crash": int(bool(ego["colision_done"])),
                "lap_done": int(bool(ego["lap_done"])),
                "time": float(ego["current_laptime"]),
                "decisions": rec.decisions,
                "place": int(ego["position"]),
                "rivals_crashed": sum(bool(o["colision_done"]) for o in rec.last[1:]),
                "redo_overtakes": len(rec.last) - 1
                - next(i for i, o in enumerate(rec.last) if o["position"] == 1),
            }
        )
        rec.out.writerow(row)
        rec.file.flush()
        rec.lap = 0 if rec.lap + 1 == self.laps else rec.lap + 1
        rec.overtakes = 0.0
        rec.decisions = 0


def paper_simulation(paper_dir, ego, rivals, laps, seed, out, name="sim_agreement",
                     contexts=range(17, 49)):
    """The paper's TestSimulation of the harness's run file config/<name>.yaml (written into the
    export `paper_dir`, which becomes the working directory, as the code expects): one run on
    f1_esp against `rivals` PurePursuit rivals, `laps` laps on each of the grid's `contexts`,
    with the harness's `ego` in place of the agent and each lap written to the open file `out`.
    Returns (sim, rec); sim.run_testing_evaluation() races it."""
    os.chdir(paper_dir)
    sys.path.insert(0, os.getcwd())
    stub_modules()
    with open(f"config/{name}.yaml", "w") as f:
        f.write(
            RUN_FILE.format(
                name=name,
                laps=laps,
                adversaries=str(["PP"] * rivals),
                agents=rivals + 1,
            )
        )
    os.makedirs(f"Data/Vehicles/{name}", exist_ok=True)
    import TrajectoryAidedLearning.TestSimulation as ts

    rec = Recorder(out)
    paper_select_agent = ts.select_agent

    def select_agent(run, conf, architecture, train=True, init=False, ma_info=[0.0, 0.0]):
        """The code's select_agent, with the harness's ego for the architecture `Harness`."""
        if architecture == "Harness":
            os.makedirs(f"Data/Vehicles/{run.path}{run.run_name}", exist_ok=True)
            return Ego(ego, run, conf, rec, seed)
        return paper_select_agent(run, conf, architecture, train, init, ma_info)

    ts.select_agent = select_agent
    ts.enumerate = context_loop(list(contexts))
    sim = ts.TestSimulation(name)
    paper_run_step = sim.run_step

    def run_step(actions):
        """The code's run_step, its observations kept for the lap's row."""
        rec.last = paper_run_step(actions)
        return rec.last

    sim.run_step = run_step
    paper_reset = sim.reset_simulation

    def reset_simulation():
        """The code's reset_simulation, its observations kept for the lap's row."""
        rec.last = paper_reset()
        return rec.last

    sim.reset_simulation = reset_simulation
    return sim, rec


def main():
    """Races the ego in the paper's simulator over the chosen contexts; one CSV row per lap."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paper_dir")
    ap.add_argument("ego", choices=["pure-pursuit", "random", "still"])
    ap.add_argument("out_csv")
    ap.add_argument("--laps", type=int, default=20)
    ap.add_argument("--rivals", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--contexts", default="17-48", type=parse_contexts)
    args = ap.parse_args()
    out = open(os.path.abspath(args.out_csv), "w", newline="")
    sim, _ = paper_simulation(args.paper_dir, args.ego, args.rivals, args.laps, args.seed, out,
                              contexts=args.contexts)
    sim.run_testing_evaluation()
    out.close()


if __name__ == "__main__":
    main()
