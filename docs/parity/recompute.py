#!/usr/bin/env python3
"""Recomputes the figures of docs/parity/README.md from the CSVs committed here.

    python3 docs/parity/recompute.py            # every table, from the repository root
    python3 docs/parity/recompute.py --check    # also compares table2.csv with the CSVs
    python3 docs/parity/recompute.py --probe    # also the initialisation probe's ratios

Standard library only. For each side folder (ctxrace, ctxrace-paper-init, ctxrace-default,
paper) and algorithm it prints:

- the training curve: the mean PG of each seed's training episodes per 500 env steps (an
  episode counts in the window of the env step it ended at; 4000 in the last), then the mean
  over the seeds that ended an episode in the window ("(n)" when only n of them did), as
  `ctxrace report --parity` bins its curves; and each seed's value per window;
- the warm-up: the env step of the first gradient step (env_steps - grad_steps of the first
  episode that ended after training began: one gradient step per env step here) and the env
  step the 32nd episode ended at;
- for each side against the paper's, the windows where the two sides' seed ranges do not
  overlap (with three seeds a side that happens by chance in 2 of 20 ways to rank six
  exchangeable values, so about one window in ten);
- the evaluation: per seed the mean over the in- and out-of-distribution contexts of
  eval/contexts.csv (PG, OT, A2A per 50 laps), then mean ± sd (n - 1) over seeds and the 95%
  percentile-bootstrap interval of the mean over seeds.

With --probe it also prints ctxrace's initialisation probe as ratios to the code's own (the table
of one_batch.md, "Initialisation probe": its CSVs are not committed, so the rounded table is the
source).

The bootstrap here is exact: every one of the n^n resamples of n seed values counted once, the
2.5% and 97.5% quantiles of their means taken as the smallest mean whose cumulative share
reaches the level. `ctxrace report` draws 10,000 resamples (deploy/src/paper.rs,
`bootstrap_ci`); with 3 seeds both give the lowest and the highest seed (each is drawn three
times with probability 1/27 = 3.7%, above 2.5%), so the intervals agree exactly.
"""

import csv
import itertools
import math
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
SIDES = ["ctxrace", "ctxrace-paper-init", "ctxrace-default", "paper"]
ALGOS = ["dreamerv3", "cmask"]
WIDTH, WINDOWS = 500, 8


def seeds(side, algo):
    folder = os.path.join(HERE, side, algo)
    if not os.path.isdir(folder):
        return []
    found = [d for d in os.listdir(folder) if d.startswith("seed")]
    return sorted(found, key=lambda d: int(d[4:]))


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def mean(xs):
    return sum(xs) / len(xs)


def sd(xs):
    if len(xs) < 2:
        return 0.0
    m = mean(xs)
    return math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1))


def bootstrap_ci(xs, level=0.95):
    """Exact percentile-bootstrap interval of the mean (all n^n resamples)."""
    n = len(xs)
    if n == 1:
        return xs[0], xs[0]
    means = sorted(sum(r) / n for r in itertools.product(xs, repeat=n))
    total = len(means)

    def quantile(q):
        for i, m in enumerate(means):
            if (i + 1) / total >= q - 1e-12:
                return m
        return means[-1]

    lo = (1 - level) / 2
    return quantile(lo), quantile(1 - lo)


def curve(episodes):
    """Per window: the seed's mean PG, or None without an episode ending there."""
    sums = [[0.0, 0] for _ in range(WINDOWS)]
    for e in episodes:
        w = min(int(int(e["env_steps"]) // WIDTH), WINDOWS - 1)
        sums[w][0] += float(e["progress"])
        sums[w][1] += 1
    return [s / n if n else None for s, n in sums]


def warmup(episodes):
    for i, e in enumerate(episodes):
        if int(e["grad_steps"]) > 0:
            first = int(e["env_steps"]) - int(e["grad_steps"])
            break
    else:
        first = None
    end32 = int(episodes[31]["env_steps"]) if len(episodes) > 31 else None
    return first, end32


def evaluation(path):
    """Per split (True: in distribution): means over the contexts of PG, OT, A2A/50."""
    out = {}
    for split in (True, False):
        ctx = [r for r in rows(path) if (r["in_distribution"] == "true") == split]
        out[split] = {k: mean([float(r[k]) for r in ctx]) for k in ("progress", "overtakes", "a2a")}
        out[split]["contexts"] = len(ctx)
    return out


def fmt(x, digits=3):
    return "-" if x is None else f"{x:.{digits}f}"


def probe():
    """one_batch.md's initialisation probe: ctxrace's draw over the code's, per seed and window."""
    table = {}
    with open(os.path.join(HERE, "one_batch.md")) as f:
        for line in f:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) == 10 and cells[0] in ("ctxrace", "paper") and cells[1].isdigit():
                table[(cells[0], cells[1], cells[2])] = [float(c) for c in cells[3:]]
    names = ["model loss", "reconstruction", "reward", "continue", "KL"]
    print()
    print("## Initialisation probe: ctxrace's draw / the code's (one_batch.md's table)")
    print("seed window: " + ", ".join(names))
    ratios = {n: [] for n in names}
    for (init, seed, window), ours in table.items():
        if init != "ctxrace":
            continue
        theirs = table[("paper", seed, window)]
        r = [o / t for o, t in zip(ours, theirs)][: len(names)]
        for n, x in zip(names, r):
            ratios[n].append(x)
        print(f"{seed} {window}: " + ", ".join(f"{x:.2f}" for x in r))
    for n in names:
        print(f"{n}: {min(ratios[n]):.2f}-{max(ratios[n]):.2f}")


def main():
    check = "--check" in sys.argv[1:]
    windows = [f"{WIDTH * i}-{WIDTH * (i + 1)}" for i in range(WINDOWS)]
    print("## Training curves: mean PG per 500 env steps, seeds averaged")
    print("| algo | side | seeds | " + " | ".join(windows) + " |")
    per_seed = {}
    for algo in ALGOS:
        for side in SIDES:
            ss = seeds(side, algo)
            if not ss:
                continue
            curves = [curve(rows(os.path.join(HERE, side, algo, s, "episodes.csv"))) for s in ss]
            per_seed[(algo, side)] = (ss, curves)
            cells = []
            for w in range(WINDOWS):
                vals = [c[w] for c in curves if c[w] is not None]
                cell = fmt(mean(vals)) if vals else "-"
                if vals and len(vals) < len(curves):
                    cell += f" ({len(vals)})"
                cells.append(cell)
            print(f"| {algo} | {side} | {len(ss)} | " + " | ".join(cells) + " |")
    print()
    print("## Per seed and window (seed order as the folders: seed0 / seed1 / ...)")
    for (algo, side), (ss, curves) in per_seed.items():
        print(f"{algo} {side}:")
        for w in range(WINDOWS):
            vals = [c[w] for c in curves]
            known = [v for v in vals if v is not None]
            rng = f"  range {fmt(min(known))}-{fmt(max(known))}" if known else ""
            print(f"  {windows[w]:>9}: " + " / ".join(fmt(v) for v in vals) + rng)
    print()
    print("## Windows where a side's seed range does not overlap the paper's")
    for (algo, side), (ss, curves) in per_seed.items():
        if side == "paper":
            continue
        paper = per_seed.get((algo, "paper"))
        if paper is None:
            continue
        for w in range(WINDOWS):
            ours = [c[w] for c in curves if c[w] is not None]
            theirs = [c[w] for c in paper[1] if c[w] is not None]
            if not ours or not theirs:
                continue
            if min(ours) > max(theirs) or max(ours) < min(theirs):
                where = "above" if min(ours) > max(theirs) else "below"
                print(f"{algo} {side} {windows[w]}: every seed {where} the paper's "
                      f"({fmt(min(ours))}-{fmt(max(ours))} against "
                      f"{fmt(min(theirs))}-{fmt(max(theirs))}; {len(ours)} and {len(theirs)} seeds)")
    print()
    print("## Warm-up: first gradient step (env step); end of the 32nd episode (env step)")
    for algo in ALGOS:
        for side in SIDES:
            ss = seeds(side, algo)
            if not ss:
                continue
            w = [warmup(rows(os.path.join(HERE, side, algo, s, "episodes.csv"))) for s in ss]
            print(f"{algo} {side}: first gradient step " + " / ".join(str(a) for a, _ in w)
                  + "; 32nd episode ends " + " / ".join(str(b) for _, b in w))
    print()
    print("## Evaluation: mean ± sd over seeds [95% bootstrap interval of the mean over seeds]")
    print("| algo | side | seeds | PG in | PG out | OT in | OT out | A2A/50 in | A2A/50 out |")
    table = {}
    for algo in ALGOS:
        for side in SIDES:
            ss = [s for s in seeds(side, algo)
                  if os.path.exists(os.path.join(HERE, side, algo, s, "eval", "contexts.csv"))]
            if not ss:
                continue
            ev = [evaluation(os.path.join(HERE, side, algo, s, "eval", "contexts.csv")) for s in ss]
            table[(algo, side)] = ev
            cells = []
            for key, digits in (("progress", 3), ("overtakes", 3), ("a2a", 1)):
                for split in (True, False):
                    xs = [e[split][key] for e in ev]
                    cell = f"{mean(xs):.{digits}f} ± {sd(xs):.{digits}f}"
                    if key != "overtakes":
                        lo, hi = bootstrap_ci(xs)
                        cell += f" [{lo:.{digits}f}, {hi:.{digits}f}]"
                    cells.append(cell)
            # PG in, PG out, OT in, OT out, A2A in, A2A out
            print(f"| {algo} | {side} | {len(ss)} | " + " | ".join(cells) + " |")
    print()
    print("## Evaluation per seed (PG in / PG out / A2A in / A2A out; contexts in, out)")
    for (algo, side), ev in table.items():
        for s, e in zip(seeds(side, algo), ev):
            print(f"{algo} {side} {s}: {e[True]['progress']:.3f} / {e[False]['progress']:.3f} / "
                  f"{e[True]['a2a']:.1f} / {e[False]['a2a']:.1f}; "
                  f"{e[True]['contexts']}, {e[False]['contexts']}")
    if "--probe" in sys.argv[1:]:
        probe()
    if check:
        print()
        print("## table2.csv (ctxrace report of the sides ctxrace and paper) against the CSVs")
        names = {"dreamerv3": ("dreamerv3", "ctxrace"), "cmask": ("cmask", "ctxrace"),
                 "paper-dreamerv3": ("dreamerv3", "paper"), "paper-cmask": ("cmask", "paper")}
        worst = 0.0
        for r in rows(os.path.join(HERE, "table2.csv")):
            ev = table[names[r["algo"]]]
            split = r["split"] == "In"
            for key, col in (("progress", "pg"), ("overtakes", "ot"), ("a2a", "a2a")):
                xs = [e[split][key] for e in ev]
                for got, want in ((mean(xs), r[col + "_mean"]), (sd(xs), r[col + "_std"])):
                    worst = max(worst, abs(got - float(want)))
        print(f"largest difference: {worst:.2g} (table2.csv rounds to 6 decimals)")
        if worst > 1e-5:
            sys.exit("table2.csv does not match the CSVs")


if __name__ == "__main__":
    main()
