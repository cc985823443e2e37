"""The agreement of ctxrace's simulator with the paper's (deploy/paper_sim_agreement.sh): per-context
rows from the raw records, and the per-ego summary with bootstrap intervals. Standard library only.

  table RAW_DIR VARIANT OUT_CSV     sim_agreement.csv: one row per simulator, ego, rival count
                                    and context (simulator,ego,rivals,context_speed,
                                    context_steer,laps,progress,overtakes,a2a; a2a per 50 laps)
                                    from the records of each rival count R in DIR (RAW_DIR for
                                    1, RAW_DIR/<R>r otherwise): DIR/paper_<ego>.csv (and
                                    DIR/paper_<ego>.<name>.csv, further runs: each context from
                                    the run with the most laps of it) and
                                    DIR/ctxrace-<VARIANT>/<ego>/episodes.csv
  compare DIR VARIANT [VARIANT..]   a markdown summary per ego with records in DIR, in and out
                                    of distribution (both |c| <= 0.15), each side's value with
                                    its 95% interval and the difference paper - ctxrace with its
                                    interval, then the contexts whose per-context difference
                                    excludes 0 (PG differences under PG_NOTED of deterministic
                                    laps left out), then the paper's OT beside its
                                    redo_overtakes.py recount where the records hold it

A split's value is the mean over its contexts of each context's mean over its laps (A2A: per 50
laps), as the protocol's. Intervals: percentile bootstrap, laps resampled with replacement within
each context (each side independently), 2000 resamples from a fixed seed; a deterministic ego's
interval is its value.
"""
import csv
import os
import random
import re
import sys

EGOS = ["pure-pursuit", "random", "still"]
METRICS = ["progress", "overtakes", "a2a"]
TRAIN_RANGE = 0.15
# per-context PG differences below this, where both sides' laps are all alike, are left out of
# the listing (how the two simulators measure progress, docs/table2/sim_agreement.md)
PG_NOTED = 0.005
RESAMPLES = 2000


def key(cv, ct):
    return (round(float(cv), 2), round(float(ct), 2))


def rival_dirs(raw):
    """(rivals, directory) of each rival count's records: RAW for 1, RAW/<R>r for R."""
    found = [(1, raw)]
    for name in sorted(os.listdir(raw)):
        if re.fullmatch(r"[0-9]+r", name) and os.path.isdir(os.path.join(raw, name)):
            found.append((int(name[:-1]), os.path.join(raw, name)))
    return found


def load_paper(raw, ego):
    """Per context: the laps' (progress, overtakes, a2a, redo_overtakes or None) of the paper's
    simulator, from RAW/paper_<ego>.csv and any further runs RAW/paper_<ego>.<name>.csv: each
    context's laps from the run that raced it most."""
    best = {}
    for name in sorted(os.listdir(raw)):
        if not (name == f"paper_{ego}.csv" or name.startswith(f"paper_{ego}.")):
            continue
        laps = {}
        with open(os.path.join(raw, name)) as f:
            for r in csv.DictReader(f):
                redo = r.get("redo_overtakes")
                laps.setdefault(key(r["context_speed"], r["context_steer"]), []).append(
                    (float(r["progress"]), float(r["overtakes"]), 50.0 * int(r["a2a"]),
                     None if redo is None else float(redo))
                )
        for c, ls in laps.items():
            if len(ls) > len(best.get(c, [])):
                best[c] = ls
    return best


def load_ctxrace(raw, variant, ego):
    """Per context: the laps' (progress, overtakes, a2a) of a ctxrace evaluation directory."""
    laps = {}
    with open(os.path.join(raw, f"ctxrace-{variant}", ego, "episodes.csv")) as f:
        for r in csv.DictReader(f):
            laps.setdefault(key(r["context_speed"], r["context_steer"]), []).append(
                (
                    float(r["progress"]),
                    float(r["overtakes"]),
                    50.0 * (r["a2a"].strip().lower() in ("true", "1")),
                )
            )
    return laps


def within(c):
    return abs(c[0]) <= TRAIN_RANGE + 1e-9 and abs(c[1]) <= TRAIN_RANGE + 1e-9


def mean(xs):
    return sum(xs) / len(xs)


def split_value(laps, contexts, m):
    return mean([mean([lap[m] for lap in laps[c]]) for c in contexts])


def resample(laps, contexts, rng):
    """Each context's laps drawn with replacement (a context whose laps are all alike as is)."""
    return {
        c: laps[c] if all(lap == laps[c][0] for lap in laps[c])
        else [rng.choice(laps[c]) for _ in laps[c]]
        for c in contexts
    }


def interval(xs):
    xs = sorted(xs)
    return xs[int(0.025 * len(xs))], xs[min(len(xs) - 1, int(0.975 * len(xs)))]


def paper_egos(raw):
    """The egos with records of the paper's simulator in RAW."""
    return [e for e in EGOS if os.path.exists(os.path.join(raw, f"paper_{e}.csv"))]


def table(raw, variant, out_csv):
    with open(out_csv, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["simulator", "ego", "rivals", "context_speed", "context_steer", "laps",
                    "progress", "overtakes", "a2a"])
        for sim in ["ctxrace", "paper"]:
            for rivals, d in rival_dirs(raw):
                for ego in paper_egos(d):
                    laps = load_paper(d, ego) if sim == "paper" else load_ctxrace(d, variant, ego)
                    for c in sorted(laps):
                        ls = laps[c]
                        w.writerow([sim, ego, rivals, c[0], c[1], len(ls)]
                                   + [f"{mean([lap[m] for lap in ls]):.6g}" for m in range(3)])


def fmt(v, lo, hi):
    return f"{v:.4f} [{lo:.4f}, {hi:.4f}]" if hi > lo else f"{v:.4f}"


def compare(raw, variants):
    rng = random.Random(20261206)
    print("| ego | split | metric | paper | " + " | ".join(
        f"ctxrace {v} | paper - ctxrace {v}" for v in variants) + " |")
    print("|---|---|---|---|" + "---|---|" * len(variants))
    per_context = []
    recounted = []
    for ego in paper_egos(raw):
        paper = load_paper(raw, ego)
        if all(lap[3] is not None for ls in paper.values() for lap in ls):
            recounted.append((ego, paper))
        sides = [load_ctxrace(raw, v, ego) for v in variants]
        for split, pick in [("in", True), ("out", False)]:
            ctxs = sorted(c for c in paper if within(c) == pick)
            boot_p = [resample(paper, ctxs, rng) for _ in range(RESAMPLES)]
            boot_c = [[resample(s, ctxs, rng) for _ in range(RESAMPLES)] for s in sides]
            for m, name in enumerate(METRICS):
                vp = split_value(paper, ctxs, m)
                bp = [split_value(b, ctxs, m) for b in boot_p]
                cells = [fmt(vp, *interval(bp))]
                for s, bc in zip(sides, boot_c):
                    vc = split_value(s, ctxs, m)
                    bcv = [split_value(b, ctxs, m) for b in bc]
                    cells.append(fmt(vc, *interval(bcv)))
                    cells.append(fmt(vp - vc, *interval([a - b for a, b in zip(bp, bcv)])))
                print(f"| {ego} | {split} ({len(ctxs)}) | {name} | " + " | ".join(cells) + " |")
        for vi, s in enumerate(sides):
            for c in sorted(paper):
                bp = [resample(paper, [c], rng) for _ in range(1000)]
                bc = [resample(s, [c], rng) for _ in range(1000)]
                for m, name in enumerate(METRICS):
                    d = split_value(paper, [c], m) - split_value(s, [c], m)
                    lo, hi = interval([split_value(a, [c], m) - split_value(b, [c], m)
                                       for a, b in zip(bp, bc)])
                    fixed = all(len(set(side[c])) == 1 for side in (paper, s))
                    small = fixed and name == "progress" and abs(d) < PG_NOTED
                    if (lo > 1e-12 or hi < -1e-12) and not small:
                        per_context.append((ego, variants[vi], c, name,
                                            split_value(paper, [c], m),
                                            split_value(s, [c], m), lo, hi))
    print()
    print(f"Contexts whose paper - ctxrace difference's 95% interval excludes 0 (PG differences "
          f"under {PG_NOTED} of deterministic laps left out):")
    print()
    print("| ego | ctxrace | c_v | c_theta | metric | paper | ctxrace | 95% interval |")
    print("|---|---|--:|--:|---|--:|--:|---|")
    for ego, v, c, name, p, x, lo, hi in per_context:
        print(f"| {ego} | {v} | {c[0]} | {c[1]} | {name} | {p:.4f} | {x:.4f} | "
              f"[{lo:.4f}, {hi:.4f}] |")
    if recounted:
        print()
        print("The paper's OT as its test loop counts it (TestSimulation.run_testing) and as "
              "DataTools/ReviewTesting/redo_overtakes.py recounts it:")
        print()
        print("| ego | split | OT, test loop | OT, redo_overtakes.py |")
        print("|---|---|---|---|")
    for ego, paper in recounted:
        for split, pick in [("in", True), ("out", False)]:
            ctxs = sorted(c for c in paper if within(c) == pick)
            boot = [resample(paper, ctxs, rng) for _ in range(RESAMPLES)]
            cells = [fmt(split_value(paper, ctxs, m),
                         *interval([split_value(b, ctxs, m) for b in boot])) for m in (1, 3)]
            print(f"| {ego} | {split} ({len(ctxs)}) | " + " | ".join(cells) + " |")


def main():
    if len(sys.argv) >= 5 and sys.argv[1] == "table":
        table(sys.argv[2], sys.argv[3], sys.argv[4])
    elif len(sys.argv) >= 4 and sys.argv[1] == "compare":
        compare(sys.argv[2], sys.argv[3:])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
