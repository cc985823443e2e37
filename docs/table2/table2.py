#!/usr/bin/env python3
"""The reduced Table II / III of issue 45, from the committed records alone (Python's standard
library, nothing else), as docs/table2/README.md plans it.

    python3 docs/table2/table2.py collect runs/table2 [ARM [RUN]] [--into DIR]   # runs -> here
    python3 docs/table2/table2.py analyse                     # tables, verdicts, ablation, masks

`collect` copies, for every run of the sweep folder whose evaluation is complete, the records
anyone needs to recompute the tables into `<R>r/<arm>/seed<S>/` (the arm is the algorithm's
name unless ARM names it, e.g. `cmask-paper-mask`; RUN: only that run; DIR instead of this
folder, e.g. docs/long): `config.toml`, `training_masks.csv` where the run wrote one,
`episodes.csv` (the training episodes), `eval/{meta.json, contexts.csv, episodes.csv}`, each
context ablation `ablation/<condition>/{meta.json, contexts.csv, episodes.csv}` and, for cMask,
`mask_training.csv` (the mask SAC's logged metrics) and `eval/mask_episodes.csv`: one row per evaluation episode with its decisions' mask sums and their
10 x 10 histogram (from `masks.csv.gz`, too large to commit). `meta.json`'s `source` (the
checkpoint's absolute path on the machine that evaluated) is kept relative to the run folder.
It keeps the run's policies, so that a later evaluation or ablation needs no retraining:
`checkpoints/best/` (and each `best-at-N/`) as the run wrote it, the last checkpoint's policy,
agent and counters
(`checkpoints/step-N/`, its manifest rewritten for those files), so the record folder is a run
folder `ctxrace eval` reads. Where the record folder held an earlier run of the same name, whether
the new `episodes.csv` reproduces it byte for byte goes to `reproduction.csv`. Evaluations of the
kept best policies (`eval-at-N/`, with their masks' episodes) are copied as `eval/` is.

`analyse` writes `table2.csv`, `table3.csv`, `hypotheses.csv`, `context_ablation.csv`,
`masks.csv`, `mask_training.csv` and `results.md` beside this file. Every interval is a 95% percentile bootstrap over
the training seeds (10,000 resamples, fixed seed), with Welch's / Student's t interval beside it.
"""

import csv
import gzip
import json
import math
import random
import re
import shutil
import sys
import zlib
from pathlib import Path

HERE = Path(__file__).resolve().parent
ALGOS = ["sac", "dreamerv3", "crssm", "cmask"]
# the arms (record folders `<R>r/<arm>/`) and the algorithm each trains: the four algorithms,
# and cMask with the mask SAC as the paper's code trained it, from alpha 1 and from 0.05
ARMS = {"sac": "sac", "dreamerv3": "dreamerv3", "crssm": "crssm", "cmask": "cmask",
        "cmask-paper-mask": "cmask", "cmask-paper-mask-alpha0.05": "cmask"}
NAMES = {"sac": "SAC", "dreamerv3": "DreamerV3", "crssm": "cRSSM", "cmask": "cMask",
         "cmask-paper-mask": "cMask (code's mask)",
         "cmask-paper-mask-alpha0.05": "cMask (code's mask, alpha0 0.05)"}
# the evaluation grid (c_v-major index k = 7 i_v + i_theta) and the context sets judged on it:
# all 49 (the paper's protocol, primary) and 17-48 (the set the code's test loop raced)
GRID, GRID_RANGE = 7, 0.3
CONTEXT_SETS = {"49": range(0, 49), "17-48": range(17, 49)}
RUN_NAME = re.compile(r"^(sac|dreamerv3|crssm|cmask)-(.+)-(\d+)r-s(\d+)$")
BOOTSTRAP = 10_000
BINS = 10
# the paper's f1_esp numbers (tab:sac, tab:means): PG in, PG out, OT in, OT out, A2A in, A2A out
PAPER = {
    (1, "sac"): (0.2045, 0.2103, None, None, None, None),
    (1, "dreamerv3"): (0.5515, 0.5255, 0.6231, 0.4096, 17.1111, 18.5850),
    (1, "crssm"): (0.5841, 0.4888, 0.4867, 0.3484, 9.3778, 14.6550),
    (1, "cmask"): (0.4300, 0.4175, 0.2120, 0.2113, 26.6444, 23.4100),
    (3, "sac"): (0.1857, 0.1756, None, None, None, None),
    (3, "dreamerv3"): (0.5479, 0.4416, 0.0667, 0.2038, 18.4667, 19.2650),
    (3, "crssm"): (0.5664, 0.4732, 0.0658, 0.0538, 20.2889, 20.3500),
    (3, "cmask"): (0.6331, 0.5335, 0.0867, 0.0759, 14.6667, 18.4063),
}
METRICS = ["pg_in", "pg_out", "ot_in", "ot_out", "a2a_in", "a2a_out"]
# the context ablation's conditions (README, H6): directory name -> what the agent was told
CONDITIONS = ["zeros", "other", "mask-1-1", "mask-0-0", "mask-1-0", "mask-0-1"]
BASELINE_LAPS = 20


def grid_index(cv, ct):
    """The grid index k = 7 i_v + i_theta of the context (c_v, c_theta)."""
    step = lambda c: round((c + GRID_RANGE) / (2 * GRID_RANGE) * (GRID - 1))
    return GRID * step(cv) + step(ct)


def in_set(cset):
    """Whether a context (c_v, c_theta) belongs to the context set `cset`."""
    return lambda cv, ct: grid_index(cv, ct) in CONTEXT_SETS[cset]


# ---------------------------------------------------------------- statistics


def mean(xs):
    return sum(xs) / len(xs)


def sd(xs):
    if len(xs) < 2:
        return float("nan")
    m = mean(xs)
    return math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1))


def percentile(sorted_xs, q):
    """Linear interpolation between order statistics (numpy's default)."""
    pos = q * (len(sorted_xs) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_xs) - 1)
    return sorted_xs[lo] + (sorted_xs[hi] - sorted_xs[lo]) * (pos - lo)


def boot_mean(xs, rng):
    """95% percentile bootstrap interval of the mean of `xs`."""
    n = len(xs)
    means = sorted(sum(rng.choice(xs) for _ in range(n)) / n for _ in range(BOOTSTRAP))
    return percentile(means, 0.025), percentile(means, 0.975)


def boot_diff(a, b, rng):
    """95% percentile bootstrap interval of mean(b) - mean(a), each group resampled on its own."""
    na, nb = len(a), len(b)
    diffs = sorted(
        sum(rng.choice(b) for _ in range(nb)) / nb - sum(rng.choice(a) for _ in range(na)) / na
        for _ in range(BOOTSTRAP)
    )
    return percentile(diffs, 0.025), percentile(diffs, 0.975)


def betacf(a, b, x):
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-14:
            break
    return h


def betainc(a, b, x):
    """Regularised incomplete beta I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    lbeta = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
    front = math.exp(lbeta + a * math.log(x) + b * math.log(1.0 - x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * betacf(a, b, x) / a
    return 1.0 - front * betacf(b, a, 1.0 - x) / b


def t_quantile(p, df):
    """Student's t quantile by bisection on its distribution function."""
    def cdf(t):
        tail = 0.5 * betainc(df / 2.0, 0.5, df / (df + t * t))
        return 1.0 - tail if t > 0 else tail

    lo, hi = -1e3, 1e3
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if cdf(mid) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def welch_diff(a, b):
    """Welch's 95% t interval of mean(b) - mean(a)."""
    va, vb = sd(a) ** 2 / len(a), sd(b) ** 2 / len(b)
    d = mean(b) - mean(a)
    se = math.sqrt(va + vb)
    if se == 0.0:
        return d, d
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    t = t_quantile(0.975, df)
    return d - t * se, d + t * se


def student_mean(xs):
    """Student's 95% t interval of the mean of `xs` (paired differences)."""
    m, se = mean(xs), sd(xs) / math.sqrt(len(xs))
    if se == 0.0:
        return m, m
    t = t_quantile(0.975, len(xs) - 1)
    return m - t * se, m + t * se


def verdict(lo, hi, direction, margin):
    """The README's verdict of one cell (section 2): the interval [lo, hi] of a difference whose
    predicted sign is `direction` (+1 or -1) holds where it excludes 0 in that direction ("holds,
    below the margin" where it also lies within +-`margin`), is contradicted where it excludes 0
    in the opposite direction (inside the margin too), equal where it lies within +-`margin` and
    contains 0, and undecided otherwise."""
    if direction * lo > 0 and direction * hi > 0:
        return "holds, below the margin" if -margin <= lo and hi <= margin else "holds"
    if direction * lo < 0 and direction * hi < 0:
        return "contradicted"
    if -margin <= lo and hi <= margin:
        return "equal"
    return "undecided"


def sign_of(verdict_text):
    """The verdict's kind: "holds, below the margin" and "holds (better)" are both "holds"."""
    return verdict_text.split(",")[0].split(" (")[0]


# ---------------------------------------------------------------- collect


def relative_source(meta, run_dir):
    source = Path(meta.get("source", ""))
    try:
        meta["source"] = str(Path(run_dir.name) / source.relative_to(run_dir.resolve()))
    except ValueError:
        parts = source.parts
        if "checkpoints" in parts:
            k = parts.index("checkpoints")
            meta["source"] = str(Path(run_dir.name, *parts[k:]))
    return meta


def copy_eval(src, dest, run_dir):
    dest.mkdir(parents=True, exist_ok=True)
    meta = json.loads((src / "meta.json").read_text())
    (dest / "meta.json").write_text(json.dumps(relative_source(meta, run_dir), indent=2) + "\n")
    for name in ["contexts.csv", "episodes.csv"]:
        shutil.copyfile(src / name, dest / name)


def mask_episodes(masks_gz, out):
    """One row per episode: decisions, the sums and squared sums of each mask component, and
    the 10 x 10 histogram of (mask_speed, mask_steer) as 100 space-separated counts."""
    episodes = {}
    with gzip.open(masks_gz, "rt", newline="") as f:
        for row in csv.DictReader(f):
            key = (float(row["context_speed"]), float(row["context_steer"]), int(row["lap"]))
            e = episodes.setdefault(key, [0, 0.0, 0.0, 0.0, 0.0, [0] * (BINS * BINS)])
            ms, mt = float(row["mask_speed"]), float(row["mask_steer"])
            e[0] += 1
            e[1] += ms
            e[2] += mt
            e[3] += ms * ms
            e[4] += mt * mt
            i, j = min(int(ms * BINS), BINS - 1), min(int(mt * BINS), BINS - 1)
            e[5][i * BINS + j] += 1
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["context_speed", "context_steer", "lap", "decisions", "sum_speed",
                    "sum_steer", "sumsq_speed", "sumsq_steer", "hist"])
        for (cv, ct, lap), e in sorted(episodes.items()):
            w.writerow([cv, ct, lap, e[0], repr(e[1]), repr(e[2]), repr(e[3]), repr(e[4]),
                        " ".join(map(str, e[5]))])


def mask_training(metrics_csv, out):
    """The mask SAC's logged training metrics (env steps, gradient steps, the temperature α, the
    entropy of the mask's distribution, the mean mask, the critic loss and, from binaries that
    log it, the critics' range over the mask grid `mask/q_spread`) of a cMask run."""
    keys = ["env_steps", "grad_steps", "mask/alpha", "mask/entropy", "mask/mean", "mask/q_loss",
            "mask/q_spread"]
    rows = read_csv(metrics_csv)
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([k.replace("mask/", "") for k in keys])
        for r in rows:
            w.writerow([r.get(k, "") for k in keys])


def keep_policies(run_dir, dest):
    """The run's best policy and its last checkpoint's policy, agent and counters (no optimiser
    state), sealed as ctxrace seals a checkpoint (`manifest.toml`: each file's bytes and CRC-32)."""
    src, out = run_dir / "checkpoints", dest / "checkpoints"
    if out.exists():
        shutil.rmtree(out)
    for best in sorted(src.glob("best*")):
        shutil.copytree(best, out / best.name)
    steps = sorted(p for p in src.iterdir() if p.name.startswith("step-"))
    last = steps[-1]
    (out / last.name).mkdir(parents=True)
    lines = []
    for name in ["agent.toml", "policy.safetensors", "state.toml"]:
        data = (last / name).read_bytes()
        (out / last.name / name).write_bytes(data)
        lines.append(f'[\"{name}\"]\nbytes = {len(data)}\ncrc32 = {zlib.crc32(data)}\n')
    (out / last.name / "manifest.toml").write_text("\n".join(lines))


def note_reproduction(dest, run_dir, arm, rivals, seed, into):
    """Whether the run's training episodes equal those of the record it replaces (in the
    records' `reproduction.csv`)."""
    old, new = dest / "episodes.csv", run_dir / "episodes.csv"
    if not old.is_file():
        return
    same = old.read_bytes() == new.read_bytes()
    path = Path(into) / "reproduction.csv"
    rows = read_csv(path) if path.is_file() else []
    rows = [r for r in rows if (r["rivals"], r["arm"], r["seed"]) != (str(rivals), arm, str(seed))]
    rows.append({"rivals": rivals, "arm": arm, "seed": seed,
                 "episodes_csv": "identical" if same else "differs"})
    rows.sort(key=lambda r: (int(r["rivals"]), r["arm"], int(r["seed"])))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["rivals", "arm", "seed", "episodes_csv"])
        w.writeheader()
        w.writerows(rows)


def collect(runs, arm=None, only=None, into=HERE):
    for run_dir in sorted(Path(runs).iterdir()):
        m = RUN_NAME.match(run_dir.name)
        if not m or (only and run_dir.name != only):
            continue
        algo, _track, rivals, seed = m.group(1), m.group(2), int(m.group(3)), int(m.group(4))
        if not (run_dir / "eval" / "contexts.csv").is_file():
            print(f"{run_dir.name}: evaluation not complete, skipped")
            continue
        dest = Path(into) / f"{rivals}r" / (arm or algo) / f"seed{seed}"
        dest.mkdir(parents=True, exist_ok=True)
        note_reproduction(dest, run_dir, arm or algo, rivals, seed, into)
        for name in ["config.toml", "episodes.csv", "training_masks.csv"]:
            if (run_dir / name).is_file():
                shutil.copyfile(run_dir / name, dest / name)
        keep_policies(run_dir, dest)
        for kept in sorted(run_dir.glob("eval-at-*")):
            if (kept / "contexts.csv").is_file():
                copy_eval(kept, dest / kept.name, run_dir)
                if (kept / "masks.csv.gz").is_file():
                    mask_episodes(kept / "masks.csv.gz", dest / kept.name / "mask_episodes.csv")
        if algo == "cmask":
            mask_training(run_dir / "metrics.csv", dest / "mask_training.csv")
        copy_eval(run_dir / "eval", dest / "eval", run_dir)
        if (run_dir / "eval" / "masks.csv.gz").is_file():
            mask_episodes(run_dir / "eval" / "masks.csv.gz", dest / "eval" / "mask_episodes.csv")
        for cond in CONDITIONS:
            src = run_dir / "ablation" / cond
            if (src / "contexts.csv").is_file():
                copy_eval(src, dest / "ablation" / cond, run_dir)
        print(f"{run_dir.name} -> {dest}")


# ---------------------------------------------------------------- analyse


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def split_values(contexts):
    """A run's per-split values: the mean over the split's contexts of each context's mean."""
    out = {}
    for split, inside in [("in", "true"), ("out", "false")]:
        rows = [r for r in contexts if r["in_distribution"] == inside]
        out[f"pg_{split}"] = mean([float(r["progress"]) for r in rows])
        out[f"ot_{split}"] = mean([float(r["overtakes"]) for r in rows])
        out[f"a2a_{split}"] = mean([float(r["a2a"]) for r in rows])
    return out


def recounted_overtakes(episodes_csv, rivals, train_range, keep):
    """OT as the paper's repository recounts it (DataTools/ReviewTesting/redo_overtakes.py at
    c0fd903): per lap, cars - leader - 1, the leader being the car furthest along at the end (0
    the ego); per split, the mean over its contexts of each context's mean. NaN for records
    written before ctxrace kept the leader (`leader` empty)."""
    per = {}
    for e in read_csv(episodes_csv):
        cv, ct = float(e["context_speed"]), float(e["context_steer"])
        if not keep(cv, ct):
            continue
        if not e.get("leader"):
            return {"ot_redo_in": float("nan"), "ot_redo_out": float("nan")}
        per.setdefault((cv, ct), []).append(rivals - int(e["leader"]))
    out = {}
    for split, inside in [("in", True), ("out", False)]:
        means = [mean(v) for (cv, ct), v in per.items()
                 if (abs(cv) <= train_range + 1e-9 and abs(ct) <= train_range + 1e-9) == inside]
        out[f"ot_redo_{split}"] = mean(means) if means else float("nan")
    return out


def summarise_episodes(episodes, train_range, laps=None, keep=lambda cv, ct: True):
    """Per-context means (A2A per 50 laps) of evaluation episodes, optionally of laps < `laps`,
    of the contexts `keep` admits."""
    per = {}
    for e in episodes:
        if laps is not None and int(e["lap"]) >= laps:
            continue
        key = (float(e["context_speed"]), float(e["context_steer"]))
        if not keep(*key):
            continue
        per.setdefault(key, []).append(e)
    rows = []
    for (cv, ct), eps in per.items():
        inside = abs(cv) <= train_range + 1e-9 and abs(ct) <= train_range + 1e-9
        rows.append({
            "in_distribution": "true" if inside else "false",
            "progress": mean([float(e["progress"]) for e in eps]),
            "overtakes": mean([float(e["overtakes"]) for e in eps]),
            "a2a": 50.0 * mean([e["a2a"] == "true" for e in eps]),
        })
    return rows


def training_pg(episodes_csv, env_steps):
    rows = read_csv(episodes_csv)
    last = [float(r["progress"]) for r in rows if float(r["env_steps"]) > 0.9 * env_steps]
    return mean(last) if last else float("nan")


def load_runs(cset):
    """Every collected run whose evaluation raced the whole context set `cset`, its values over
    that set's contexts: {(rivals, arm): [run]}."""
    runs = {}
    keep = in_set(cset)
    for rivals in [1, 3]:
        for algo in ARMS:
            for seed_dir in sorted((HERE / f"{rivals}r" / algo).glob("seed*")):
                meta = json.loads((seed_dir / "eval" / "meta.json").read_text())
                config = (seed_dir / "config.toml").read_text()
                steps = float(re.search(r"^env_steps\s*=\s*(\S+)", config, re.M).group(1))
                contexts = [c for c in read_csv(seed_dir / "eval" / "contexts.csv")
                            if keep(float(c["context_speed"]), float(c["context_steer"]))]
                if len(contexts) != len(CONTEXT_SETS[cset]):
                    continue
                run = split_values(contexts)
                run.update(recounted_overtakes(seed_dir / "eval" / "episodes.csv", rivals,
                                               meta["train_range"], keep))
                run["train_pg"] = training_pg(seed_dir / "episodes.csv", steps)
                run["seed"] = int(seed_dir.name[4:])
                run["dir"] = seed_dir
                run["train_range"] = meta["train_range"]
                run["keep"] = keep
                runs.setdefault((rivals, algo), []).append(run)
    return runs


def fmt(x, digits=3):
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def table2(runs, rng):
    rows = []
    for (rivals, algo), rs in sorted(runs.items(), key=lambda kv: (kv[0][0], list(ARMS).index(kv[0][1]))):
        row = {"rivals": rivals, "algo": algo, "seeds": len(rs)}
        # the recounted OT resamples from its own seed: the other intervals stay as they were
        recount_rng = random.Random(56)
        for k in METRICS + ["train_pg", "ot_redo_in", "ot_redo_out"]:
            xs = [r[k] for r in rs]
            row[k] = mean(xs)
            row[f"{k}_sd"] = sd(xs)
            draw = recount_rng if k.startswith("ot_redo") else rng
            lo, hi = boot_mean(xs, draw) if len(xs) > 1 else (float("nan"), float("nan"))
            row[f"{k}_lo"], row[f"{k}_hi"] = lo, hi
        for k, v in zip(METRICS, PAPER[(rivals, ARMS[algo])]):
            row[f"paper_{k}"] = v
        rows.append(row)
    return rows


def relative(out_value, in_value):
    return 100.0 * (out_value - in_value) / abs(in_value)


def table3(runs, rng):
    rows = []
    for (rivals, algo), rs in sorted(runs.items(), key=lambda kv: (kv[0][0], list(ARMS).index(kv[0][1]))):
        p = PAPER[(rivals, ARMS[algo])]
        per_seed = [relative(r["pg_out"], r["pg_in"]) for r in rs]
        d_a2a = [r["a2a_out"] - r["a2a_in"] for r in rs]
        lo, hi = boot_mean(per_seed, rng) if len(rs) > 1 else (float("nan"),) * 2
        row = {
            "rivals": rivals, "algo": algo, "seeds": len(rs),
            "d_pg_pct": relative(mean([r["pg_out"] for r in rs]), mean([r["pg_in"] for r in rs])),
            "d_pg_pct_per_seed": mean(per_seed), "d_pg_pct_lo": lo, "d_pg_pct_hi": hi,
            "d_a2a_pct": relative(mean([r["a2a_out"] for r in rs]), mean([r["a2a_in"] for r in rs]))
            if mean([r["a2a_in"] for r in rs]) else float("nan"),
            "d_a2a_abs": mean(d_a2a),
            "paper_d_pg_pct": relative(p[1], p[0]),
            "paper_d_a2a_pct": relative(p[5], p[4]) if p[4] else None,
        }
        rows.append(row)
    return rows


def cell(cells, rng, hyp, label, rivals, split, a, b, direction, margin, kind="order"):
    """One hypothesis cell: the difference mean(b) - mean(a) of per-seed values."""
    base = {"hypothesis": hyp, "comparison": label, "rivals": rivals, "split": split,
            "n_a": len(a), "n_b": len(b), "margin": margin, "direction": direction}
    if len(a) < 2 or len(b) < 2:
        cells.append({**base, "estimate": mean(b) - mean(a) if a and b else float("nan"),
                      "boot_lo": float("nan"), "boot_hi": float("nan"),
                      "welch_lo": float("nan"), "welch_hi": float("nan"),
                      "verdict": f"not judged ({min(len(a), len(b))} seed(s))", "weak": ""})
        return
    lo, hi = boot_diff(a, b, rng)
    wlo, whi = welch_diff(a, b)
    if kind == "noninferior":
        v = "holds" if lo > -margin else "contradicted" if hi < -margin else "undecided"
        if lo > 0:
            v = "holds (better)"
        wv = "holds" if wlo > -margin else "contradicted" if whi < -margin else "undecided"
    elif kind == "equal":
        v = "holds" if -margin <= lo and hi <= margin else (
            "contradicted" if lo > margin or hi < -margin else "undecided")
        wv = "holds" if -margin <= wlo and whi <= margin else (
            "contradicted" if wlo > margin or whi < -margin else "undecided")
    else:
        v = verdict(lo, hi, direction, margin)
        wv = verdict(wlo, whi, direction, margin)
    weak = "weak" if sign_of(v) in ("holds", "contradicted", "equal") and sign_of(wv) != sign_of(v) else ""
    cells.append({**base, "estimate": mean(b) - mean(a), "boot_lo": lo, "boot_hi": hi,
                  "welch_lo": wlo, "welch_hi": whi, "verdict": v, "weak": weak})


def hypotheses(runs, rng, cm="cmask"):
    """The cells of H1-H5 and H8, with the arm `cm` as cMask; for another arm than `cmask`, only
    the cells that compare it, at the rival counts it was raced at. (Every cell is computed
    first, so that the bootstrap's draws, and every later interval, do not depend on which.)"""
    cells = []
    get = lambda rivals, algo, key: [r[key] for r in runs.get((rivals, algo), [])]
    ratio = lambda rivals, algo: [(r["pg_out"] - r["pg_in"]) / r["pg_in"] for r in runs.get((rivals, algo), [])]
    d_a2a = lambda rivals, algo: [r["a2a_out"] - r["a2a_in"] for r in runs.get((rivals, algo), [])]
    for rivals in [1, 3]:
        for split in ["in", "out"]:
            for algo in ["dreamerv3", "crssm", cm]:
                cell(cells, rng, "H1", f"{NAMES[algo]} - SAC", rivals, split,
                     get(rivals, "sac", f"pg_{split}"), get(rivals, algo, f"pg_{split}"), +1, 0.05)
        for algo in ["crssm", cm]:
            cell(cells, rng, "H2", f"r({NAMES[algo]}) - r(DreamerV3)", rivals, "out vs in",
                 ratio(rivals, "dreamerv3"), ratio(rivals, algo), +1, 0.10)
            cell(cells, rng, "H2b", f"dA2A({NAMES[algo]}) - dA2A(DreamerV3)", rivals, "out - in",
                 d_a2a(rivals, "dreamerv3"), d_a2a(rivals, algo), -1, 5.0)
        for split in ["in", "out"]:
            for algo in ["crssm", cm]:
                cell(cells, rng, "H3", f"A2A(DreamerV3) - A2A({NAMES[algo]})", rivals, split,
                     get(rivals, algo, f"a2a_{split}"), get(rivals, "dreamerv3", f"a2a_{split}"), +1, 5.0)
        cell(cells, rng, "H4", f"PG({NAMES[cm]}) - PG(cRSSM), non-inferiority", rivals, "out",
             get(rivals, "crssm", "pg_out"), get(rivals, cm, "pg_out"), +1, 0.05, "noninferior")
        cell(cells, rng, "H4b", f"PG({NAMES[cm]}) - PG(cRSSM)", rivals, "in",
             get(rivals, "crssm", "pg_in"), get(rivals, cm, "pg_in"), +1, 0.05)
        for split, k in [("in", 0), ("out", 1)]:
            dreamers = ["dreamerv3", "crssm", cm]
            for i, x in enumerate(dreamers):
                for y in dreamers[i + 1:]:
                    d = PAPER[(rivals, ARMS[y])][k] - PAPER[(rivals, ARMS[x])][k]
                    hi_algo, lo_algo = (y, x) if d > 0 else (x, y)
                    if abs(d) >= 0.05:
                        cell(cells, rng, "H5", f"{NAMES[hi_algo]} > {NAMES[lo_algo]}", rivals, split,
                             get(rivals, lo_algo, f"pg_{split}"), get(rivals, hi_algo, f"pg_{split}"), +1, 0.05)
                    else:
                        cell(cells, rng, "H5", f"{NAMES[y]} = {NAMES[x]}", rivals, split,
                             get(rivals, x, f"pg_{split}"), get(rivals, y, f"pg_{split}"), 0, 0.05, "equal")
        for split in ["in", "out"]:
            for algo in ["crssm", cm]:
                cell(cells, rng, "H8", f"OT(DreamerV3) - OT({NAMES[algo]})", rivals, split,
                     get(rivals, algo, f"ot_{split}"), get(rivals, "dreamerv3", f"ot_{split}"), +1, 0.05)
    if cm != "cmask":
        cells = [c for c in cells if NAMES[cm] in c["comparison"] and runs.get((c["rivals"], cm))]
    return cells


def kendall_tau(ours, paper):
    pairs = [(i, j) for i in range(len(ours)) for j in range(i + 1, len(ours))]
    s = sum(math.copysign(1, (ours[i] - ours[j]) * (paper[i] - paper[j])) for i, j in pairs
            if (ours[i] - ours[j]) * (paper[i] - paper[j]) != 0)
    return s / len(pairs)


def ablation(runs, rng):
    """H6: per seed, condition minus the main evaluation's laps 0-19, per split."""
    rows, cells = [], []
    for (rivals, algo), rs in sorted(runs.items()):
        if ARMS[algo] not in ("crssm", "cmask"):
            continue
        for r in rs:
            main_eps = read_csv(r["dir"] / "eval" / "episodes.csv")
            true = split_values(summarise_episodes(main_eps, r["train_range"], BASELINE_LAPS,
                                                   r["keep"]))
            rows.append({"algo": algo, "rivals": rivals, "seed": r["seed"], "condition": "true",
                         **true})
            for cond in CONDITIONS:
                path = r["dir"] / "ablation" / cond / "episodes.csv"
                if path.is_file():
                    v = split_values(summarise_episodes(read_csv(path), r["train_range"],
                                                        keep=r["keep"]))
                    rows.append({"algo": algo, "rivals": rivals, "seed": r["seed"],
                                 "condition": cond, **v})
    for (rivals, algo) in sorted({(r["rivals"], r["algo"]) for r in rows}):
        mine = [r for r in rows if (r["rivals"], r["algo"]) == (rivals, algo)]
        true = {r["seed"]: r for r in mine if r["condition"] == "true"}
        for cond in CONDITIONS:
            got = {r["seed"]: r for r in mine if r["condition"] == cond}
            seeds = sorted(set(got) & set(true))
            if not seeds:
                continue
            for split in ["in", "out"]:
                for key, margin, used_dir in [("pg", 0.05, -1), ("a2a", 5.0, +1)]:
                    diffs = [got[s][f"{key}_{split}"] - true[s][f"{key}_{split}"] for s in seeds]
                    if len(diffs) > 1:
                        lo, hi = boot_mean(diffs, rng)
                        slo, shi = student_mean(diffs)
                    else:
                        lo = hi = slo = shi = float("nan")
                    cells.append({"algo": algo, "rivals": rivals, "condition": cond,
                                  "split": split, "metric": key, "seeds": len(seeds),
                                  "estimate": mean(diffs), "boot_lo": lo, "boot_hi": hi,
                                  "t_lo": slo, "t_hi": shi,
                                  "verdict": "not judged (1 seed)" if len(diffs) < 2 else
                                  verdict(lo, hi, used_dir, margin)})
    return rows, cells


def mask_stats(hist_rows, rng, shuffles=200, keep=lambda cv, ct: True):
    """H7 of one cMask agent: per component the SD across contexts of the per-context mean mask,
    and the plug-in mutual information (bits) between the binned mask and the context, each
    with its episode-shuffled baseline (mean over `shuffles` shufflings of the context labels)."""
    eps = []
    for r in hist_rows:
        if not keep(float(r["context_speed"]), float(r["context_steer"])):
            continue
        eps.append(((float(r["context_speed"]), float(r["context_steer"])), int(r["decisions"]),
                    float(r["sum_speed"]), float(r["sum_steer"]), list(map(int, r["hist"].split()))))
    labels = [e[0] for e in eps]

    def stats(labels):
        per = {}
        for label, e in zip(labels, eps):
            p = per.setdefault(label, [0, 0.0, 0.0, [0] * (BINS * BINS)])
            p[0] += e[1]
            p[1] += e[2]
            p[2] += e[3]
            p[3] = [x + y for x, y in zip(p[3], e[4])]
        sd_speed = sd([p[1] / p[0] for p in per.values()])
        sd_steer = sd([p[2] / p[0] for p in per.values()])
        total = sum(p[0] for p in per.values())

        def mi(project):
            joint = {}
            for label, p in per.items():
                for k, count in enumerate(p[3]):
                    if count:
                        b = project(k)
                        joint[(label, b)] = joint.get((label, b), 0) + count
            pm, pc = {}, {}
            for (label, b), count in joint.items():
                pm[b] = pm.get(b, 0) + count
                pc[label] = pc.get(label, 0) + count
            return sum(c / total * math.log2(c * total / (pm[b] * pc[label]))
                       for (label, b), c in joint.items())

        return {"sd_speed": sd_speed, "sd_steer": sd_steer,
                "mi_speed": mi(lambda k: k // BINS), "mi_steer": mi(lambda k: k % BINS),
                "mi_joint": mi(lambda k: k)}

    observed = stats(labels)
    shuffled = {k: 0.0 for k in observed}
    for _ in range(shuffles):
        perm = labels[:]
        rng.shuffle(perm)
        for k, v in stats(perm).items():
            shuffled[k] += v / shuffles
    total = sum(e[1] for e in eps)
    return observed, shuffled, {
        "mean_speed": sum(e[2] for e in eps) / total, "mean_steer": sum(e[3] for e in eps) / total,
    }


def masks(runs, rng):
    rows = []
    for (rivals, algo), rs in sorted(runs.items()):
        if ARMS[algo] != "cmask":
            continue
        for r in rs:
            path = r["dir"] / "eval" / "mask_episodes.csv"
            if not path.is_file():
                continue
            observed, shuffled, means = mask_stats(read_csv(path), rng, keep=r["keep"])
            row = {"rivals": rivals, "arm": algo, "seed": r["seed"], **means}
            for k in observed:
                row[k] = observed[k]
                row[f"{k}_shuffled"] = shuffled[k]
                row[f"{k}_excess"] = observed[k] - shuffled[k]
            rows.append(row)
    cells = []
    for rivals, arm in sorted({(r["rivals"], r["arm"]) for r in rows}):
        mine = [r for r in rows if (r["rivals"], r["arm"]) == (rivals, arm)]
        for k, margin in [("sd_speed", 0.02), ("sd_steer", 0.02), ("mi_speed", 0.01),
                          ("mi_steer", 0.01), ("mi_joint", 0.01)]:
            xs = [r[f"{k}_excess"] for r in mine]
            if len(xs) < 2:
                continue
            lo, hi = boot_mean(xs, rng)
            # an excess wholly inside the margin is no dependence, even where it lies above 0
            v = "no dependence" if -margin <= lo and hi <= margin else "holds" if lo > 0 else "undecided"
            cells.append({"rivals": rivals, "arm": arm, "statistic": k, "seeds": len(xs), "excess": mean(xs),
                          "boot_lo": lo, "boot_hi": hi, "margin": margin, "verdict": v})
    return rows, cells


def mask_training_rows(runs):
    """Per cMask run, the last 10% of its training's logged mask-SAC metrics: mean α, entropy,
    mask and, where logged, Q spread over the mask grid, the spread in units of α (the actor's
    trade: a mask worth less than about α nats of entropy stays where the entropy puts it)."""
    rows = []
    for (rivals, algo), rs in sorted(runs.items()):
        path_of = [(r, r["dir"] / "mask_training.csv") for r in rs] if ARMS[algo] == "cmask" else []
        for r, path in path_of:
            if not path.is_file():
                continue
            logged = read_csv(path)
            end = max(float(x["env_steps"]) for x in logged)
            last = [x for x in logged if float(x["env_steps"]) > 0.9 * end]
            row = {"rivals": rivals, "arm": algo, "seed": r["seed"]}
            for k in ["alpha", "entropy", "mean", "q_spread"]:
                xs = [float(x[k]) for x in last if x.get(k)]
                row[k] = mean(xs) if xs else float("nan")
            row["q_spread_over_alpha"] = row["q_spread"] / row["alpha"]
            rows.append(row)
    return rows


def write_csv(name, rows, folder=HERE):
    """`rows` (dicts; the union of their keys as columns, floats to 6 digits) as `folder`/`name`."""
    if not rows:
        return
    keys = list(rows[0].keys())
    for r in rows[1:]:
        keys += [k for k in r if k not in keys]
    with open(folder / name, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()
                        if k != "dir"})


def run_rows(runs):
    """One markdown row per run: its training PG (last 10% of env steps) and split values."""
    rows = []
    for (rivals, algo), rs in sorted(runs.items(), key=lambda kv: (kv[0][0], list(ARMS).index(kv[0][1]))):
        for r in sorted(rs, key=lambda r: r["seed"]):
            rows.append(f"| {rivals} | {NAMES[algo]} | {r['seed']} | {fmt(r['train_pg'])} | "
                        f"{fmt(r['pg_in'])} | {fmt(r['pg_out'])} | {r['ot_in']:+.2f} / {r['ot_out']:+.2f} | "
                        f"{fmt(r['a2a_in'], 1)} / {fmt(r['a2a_out'], 1)} |")
    return rows


def markdown(cset, runs, t2, t3, cells, abl_cells, mask_rows, mask_cells):
    """The results on the context set `cset`, one section."""
    n_in = sum(1 for k in CONTEXT_SETS[cset]
               if all(abs(-GRID_RANGE + 2 * GRID_RANGE * i / (GRID - 1)) <= 0.15 + 1e-9
                      for i in divmod(k, GRID)))
    title = ("all 49 contexts: the paper's protocol" if cset == "49"
             else f"contexts {cset}: the set the paper's code's test loop raced")
    out = [f"# On {title}", ""]
    out += [f"## Runs (contexts {cset}; in = the {n_in} within ±0.15)", "",
            "| rivals | algo | seed | training PG, last 10% | PG in | PG out | OT in / out | A2A in / out (per 50 laps) |",
            "|--:|---|--:|--:|--:|--:|---|---|"]
    out += run_rows(runs) + [""]
    out += [f"## Table II (contexts {cset}; seed means, 95% bootstrap interval over seeds; paper beside)", "",
            "| rivals | algo | seeds | training PG | PG in | PG out | OT in | OT out | A2A in | A2A out |",
            "|---|---|--:|--:|---|---|---|---|---|---|"]
    def c(r, k, d=3, paper=None):
        """A seed mean, its interval (over 2 seeds or more) and the paper's value (or –)."""
        p = r.get(paper or f"paper_{k}")
        ci = f" [{fmt(r[k + '_lo'], d)}, {fmt(r[k + '_hi'], d)}]" if r["seeds"] > 1 else ""
        return f"{fmt(r[k], d)}{ci} ({fmt(p, d) if p is not None else '–'})"
    for r in t2:
        out.append(f"| {r['rivals']} | {NAMES[r['algo']]} | {r['seeds']} | {fmt(r['train_pg'])} | "
                   + " | ".join(c(r, k, 1 if k.startswith("a2a") else 3) for k in METRICS) + " |")
    recounted = [r for r in t2 if not math.isnan(r["ot_redo_in"])]
    if recounted:
        out += ["", "OT as the paper's repository recounts a lap (`redo_overtakes.py`: cars - leader - 1; "
                "groups whose every run kept the leader; paper's OT beside):", "",
                "| rivals | algo | seeds | OT recount in | OT recount out |", "|---|---|--:|---|---|"]
        for r in recounted:
            recount = [c(r, k, paper=p)
                       for k, p in [("ot_redo_in", "paper_ot_in"), ("ot_redo_out", "paper_ot_out")]]
            out.append(f"| {r['rivals']} | {NAMES[r['algo']]} | {r['seeds']} | " + " | ".join(recount) + " |")
    out += ["", "## Table III (relative change in to out, %; paper recomputed from its Table II beside)", "",
            "| rivals | algo | seeds | ΔPG % (of seed means) | ΔPG % per seed [95% CI] | ΔA2A % | ΔA2A (per 50 laps) | paper ΔPG % | paper ΔA2A % |",
            "|---|---|--:|--:|---|--:|--:|--:|--:|"]
    for r in t3:
        ci = f" [{fmt(r['d_pg_pct_lo'], 1)}, {fmt(r['d_pg_pct_hi'], 1)}]" if r["seeds"] > 1 else ""
        out.append(f"| {r['rivals']} | {NAMES[r['algo']]} | {r['seeds']} | {fmt(r['d_pg_pct'], 1)} | "
                   f"{fmt(r['d_pg_pct_per_seed'], 1)}{ci} | {fmt(r['d_a2a_pct'], 1)} | "
                   f"{fmt(r['d_a2a_abs'], 1)} | {fmt(r['paper_d_pg_pct'], 1)} | "
                   f"{fmt(r['paper_d_a2a_pct'], 1)} |")
    out += ["", "## Hypothesis cells", "",
            "| H | comparison | rivals | split | n | estimate | bootstrap 95% | Welch 95% | margin | verdict |",
            "|---|---|--:|---|---|--:|---|---|--:|---|"]
    for c in cells:
        out.append(f"| {c['hypothesis']} | {c['comparison']} | {c['rivals']} | {c['split']} | "
                   f"{c['n_a']}/{c['n_b']} | {fmt(c['estimate'])} | [{fmt(c['boot_lo'])}, {fmt(c['boot_hi'])}] | "
                   f"[{fmt(c['welch_lo'])}, {fmt(c['welch_hi'])}] | {c['margin']} | {c['verdict']}"
                   f"{' (' + c['weak'] + ')' if c['weak'] else ''} |")
    out += ["", "### Verdicts per hypothesis", ""]
    for h in sorted({c["hypothesis"] for c in cells}):
        mine = [c for c in cells if c["hypothesis"] == h]
        judged = [c for c in mine if not c["verdict"].startswith("not judged")]
        tally = {}
        for c in judged:
            tally[sign_of(c["verdict"])] = tally.get(sign_of(c["verdict"]), 0) + 1
        if not judged:
            v = "not judged"
        elif any(sign_of(c["verdict"]) == "contradicted" for c in judged):
            v = "contradicted"
        elif len(judged) == len(mine) and all(sign_of(c["verdict"]) in ("holds", "equal" if h == "H5" else "holds") for c in judged):
            v = "holds"
        else:
            k = sum(sign_of(c["verdict"]) == "holds" for c in judged)
            v = f"partly ({k} of {len(mine)} cells)" if k else "undecided"
        out.append(f"- **{h}**: {v}; cells: " + ", ".join(f"{k} {n}" for k, n in sorted(tally.items()))
                   + f" ({len(mine) - len(judged)} not judged)")
    taus = []
    for rivals in [1, 3]:
        for k, split in [(0, "in"), (1, "out")]:
            algos = ["dreamerv3", "crssm", "cmask"]
            ours = [mean([r[f"pg_{split}"] for r in t2 if (r["rivals"], r["algo"]) == (rivals, a)] or [float("nan")]) for a in algos]
            if not any(math.isnan(x) for x in ours):
                taus.append((rivals, split, kendall_tau(ours, [PAPER[(rivals, a)][k] for a in algos])))
    if taus:
        out.append("- H5 Kendall's τ (Dreamer variants' PG order, ours against the paper's): "
                   + ", ".join(f"{r} rival(s) {s}: {t:+.2f}" for r, s, t in taus))
    if abl_cells:
        out += ["", "## Context ablation (H6): condition minus true context (laps 0-19), paired over seeds", "",
                "| algo | rivals | condition | split | metric | seeds | estimate | bootstrap 95% | t 95% | verdict (used?) |",
                "|---|--:|---|---|---|--:|--:|---|---|---|"]
        for c in abl_cells:
            out.append(f"| {NAMES[c['algo']]} | {c['rivals']} | {c['condition']} | {c['split']} | {c['metric']} | "
                       f"{c['seeds']} | {fmt(c['estimate'])} | [{fmt(c['boot_lo'])}, {fmt(c['boot_hi'])}] | "
                       f"[{fmt(c['t_lo'])}, {fmt(c['t_hi'])}] | {c['verdict']} |")
    if mask_rows:
        out += ["", "## cMask's masks (H7): observed, shuffled baseline, per agent", "",
                "| rivals | arm | seed | mean m_v | mean m_θ | SD m_v across contexts (shuffled) | SD m_θ (shuffled) | MI m_v bits (shuffled) | MI m_θ (shuffled) | MI joint (shuffled) |",
                "|--:|---|--:|--:|--:|---|---|---|---|---|"]
        for r in mask_rows:
            out.append(f"| {r['rivals']} | {NAMES[r['arm']]} | {r['seed']} | {fmt(r['mean_speed'])} | {fmt(r['mean_steer'])} | "
                       + " | ".join(f"{fmt(r[k], 4)} ({fmt(r[k + '_shuffled'], 4)})"
                                    for k in ["sd_speed", "sd_steer", "mi_speed", "mi_steer", "mi_joint"]) + " |")
        for c in mask_cells:
            out.append(f"- {NAMES[c['arm']]}, {c['rivals']} rival(s), {c['statistic']} excess {fmt(c['excess'], 4)} "
                       f"[{fmt(c['boot_lo'], 4)}, {fmt(c['boot_hi'], 4)}] over {c['seeds']} seeds: {c['verdict']}")
    return "\n".join(out) + "\n"


def training_markdown(trained):
    """The mask SACs' state at the end of training, whatever the context set."""
    out = []
    if trained:
        out += ["# cMask's mask SAC at the end of training (last 10% of env steps)", "",
                "| rivals | arm | seed | α | entropy (nats) | mean mask | Q spread over the mask grid | spread / α |",
                "|--:|---|--:|--:|--:|--:|--:|--:|"]
        for r in trained:
            out.append(f"| {r['rivals']} | {NAMES[r['arm']]} | {r['seed']} | {fmt(r['alpha'])} | {fmt(r['entropy'])} | "
                       f"{fmt(r['mean'])} | {fmt(r['q_spread'], 4)} | {fmt(r['q_spread_over_alpha'], 4)} |")
    return "\n".join(out) + "\n"


def analyse():
    files = {name: [] for name in ["table2", "table3", "hypotheses", "context_ablation",
                                   "context_ablation_cells", "masks"]}
    md = ["# Results (written by `python3 docs/table2/table2.py analyse`)", ""]
    for cset in CONTEXT_SETS:
        runs = load_runs(cset)
        if not runs:
            continue
        # each set's resamples from the same seed: its intervals do not move with the other's runs
        rng = random.Random(45)
        t2, t3 = table2(runs, rng), table3(runs, rng)
        cells = hypotheses(runs, rng)
        for arm in ARMS:
            if arm.startswith("cmask-") and any(a == arm for _, a in runs):
                cells += hypotheses(runs, rng, arm)
        abl_rows, abl_cells = ablation(runs, rng)
        mask_rows, mask_cells = masks(runs, rng)
        for name, rows in [("table2", t2), ("table3", t3), ("hypotheses", cells),
                           ("context_ablation", abl_rows), ("context_ablation_cells", abl_cells),
                           ("masks", mask_rows + mask_cells)]:
            files[name] += [{"contexts": cset, **r} for r in rows]
        md.append(markdown(cset, runs, t2, t3, cells, abl_cells, mask_rows, mask_cells))
    if not any(files.values()):
        sys.exit(f"no runs under {HERE}/<R>r/<arm>/seed<S>/: run `collect` first")
    trained = mask_training_rows(load_runs("17-48"))
    md.append(training_markdown(trained))
    for name, rows in files.items():
        write_csv(f"{name}.csv", rows)
    write_csv("mask_training.csv", trained)
    (HERE / "results.md").write_text("\n".join(md))
    print((HERE / "results.md").read_text())


if __name__ == "__main__":
    args = sys.argv[1:]
    into = HERE
    if len(args) >= 2 and args[-2] == "--into":
        into, args = Path(args[-1]), args[:-2]
    if 2 <= len(args) <= 4 and args[0] == "collect":
        collect(*args[1:], into=into)
    elif args == ["analyse"]:
        analyse()
    else:
        sys.exit(__doc__)
