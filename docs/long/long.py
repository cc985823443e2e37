#!/usr/bin/env python3
"""Issue 56's long runs, analysed by the rules of docs/long/README.md (section 3), from the
committed records alone (Python's standard library; the statistics are docs/table2/table2.py's).

    python3 docs/long/long.py analyse     # -> docs/long/{mask_over_training.csv,
                                          #    mask_at_evaluations.csv, races.csv, results.md,
                                          #    mask_over_training.svg}

Records: `<R>r/<arm>/seed<S>/` as `deploy/campaign.sh docs/long` collects them
(`mask_training.csv`, `training_masks.csv`, `eval-at-<N>/` and `eval/`).
"""

import math
import random
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "table2"))
import table2  # noqa: E402  (the statistics and readers, one copy)

MARGIN_BITS = 0.01  # H7's margin on the MI excess (docs/table2/README.md section 2)
WINDOW = 10_000  # env steps per window of M2
SHUFFLES = 200
BINS = 10


def runs():
    """Every collected long run: (rivals, arm, seed, folder)."""
    for rdir in sorted(HERE.glob("*r")):
        for adir in sorted(p for p in rdir.iterdir() if p.is_dir()):
            for sdir in sorted(adir.glob("seed*")):
                yield int(rdir.name[:-1]), adir.name, int(sdir.name[4:]), sdir


def evaluations(folder):
    """The run's evaluations by env steps: eval-at-<N>/ and, at the run's end, eval/."""
    config = (folder / "config.toml").read_text()
    end = int(float(re.search(r"^env_steps\s*=\s*(\S+)", config, re.M).group(1)))
    found = {int(p.name.split("-")[-1]): p for p in folder.glob("eval-at-*")}
    if (folder / "eval" / "contexts.csv").is_file():
        found[end] = folder / "eval"
    return dict(sorted(found.items()))


def mi_excess(pairs, rng):
    """The plug-in MI (bits) between a label and a bin in `pairs`, minus its mean over
    `SHUFFLES` shufflings of the labels."""

    def mi(items):
        n = len(items)
        joint, pl, pb = {}, {}, {}
        for label, b in items:
            joint[(label, b)] = joint.get((label, b), 0) + 1
            pl[label] = pl.get(label, 0) + 1
            pb[b] = pb.get(b, 0) + 1
        return sum(c / n * math.log2(c * n / (pl[l] * pb[b])) for (l, b), c in joint.items())

    observed = mi(pairs)
    labels = [label for label, _ in pairs]
    shuffled = 0.0
    for _ in range(SHUFFLES):
        rng.shuffle(labels)
        shuffled += mi(list(zip(labels, (b for _, b in pairs)))) / SHUFFLES
    return observed - shuffled


def mask_bin(m):
    return min(int(m * BINS), BINS - 1)


def context_bin(c, train_range, k=5):
    return min(int((c + train_range) / (2 * train_range) * k), k - 1)


def over_training(folder, rng, train_range=0.15):
    """M2 and M3 of one run: per window of env steps, the MI excess of each mask component with
    the episode's context (5 x 5 bins of the training range), and the mask SAC's alpha,
    entropy and Q spread at the window's last logged step."""
    masks = table2.read_csv(folder / "training_masks.csv") if (folder / "training_masks.csv").is_file() else []
    logged = table2.read_csv(folder / "mask_training.csv") if (folder / "mask_training.csv").is_file() else []
    rows = []
    ends = sorted({(int(r["env_steps"]) - 1) // WINDOW for r in masks + logged})
    for w in ends:
        lo, hi = w * WINDOW, (w + 1) * WINDOW
        eps = [r for r in masks if lo < int(r["env_steps"]) <= hi]
        row = {"env_steps": hi, "episodes": len(eps)}
        for part, key in [("speed", "mask_speed"), ("steer", "mask_steer")]:
            pairs = [((context_bin(float(r["context_speed"]), train_range),
                       context_bin(float(r["context_steer"]), train_range)),
                      mask_bin(float(r[key]))) for r in eps]
            row[f"mi_{part}_excess"] = mi_excess(pairs, rng) if len(pairs) > 1 else float("nan")
        last = [r for r in logged if lo < int(r["env_steps"]) <= hi]
        for k in ["grad_steps", "alpha", "entropy", "q_spread"]:
            row[k] = float(last[-1][k]) if last and last[-1].get(k) else float("nan")
        rows.append(row)
    return rows


def first_below(rows, key, bound):
    """The first window whose `key` is below `bound` (gradient steps), or None."""
    hit = [r["grad_steps"] for r in rows if r[key] < bound]
    return min(hit) if hit else None


def svg(series, key, title):
    """A line per seed of `key` against gradient steps: an SVG group and its size, or None
    without a point."""
    w, h, pad = 480, 240, 40
    points = [(r["grad_steps"], r[key]) for s in series.values() for r in s
              if not math.isnan(r[key]) and not math.isnan(r["grad_steps"])]
    if not points:
        return None
    x0, x1 = 0, max(x for x, _ in points) or 1
    y0, y1 = min(0.0, min(y for _, y in points)), max(y for _, y in points) or 1
    sx = lambda x: pad + (x - x0) / (x1 - x0) * (w - 2 * pad)
    sy = lambda y: h - pad - (y - y0) / ((y1 - y0) or 1) * (h - 2 * pad)
    out = [f'<g><text x="{pad}" y="20" font-size="13">{title}</text>',
           f'<text x="{w - pad}" y="{h - 8}" font-size="11" text-anchor="end">gradient steps '
           f'(0-{x1:.0f})</text><text x="4" y="{pad}" font-size="11">{y1:.3g}</text>'
           f'<text x="4" y="{h - pad}" font-size="11">{y0:.3g}</text>']
    colours = ["#c0392b", "#2471a3", "#229954", "#7d3c98", "#b9770e", "#17a589"]
    for i, (name, s) in enumerate(sorted(series.items())):
        pts = " ".join(f"{sx(r['grad_steps']):.1f},{sy(r[key]):.1f}" for r in s
                       if not math.isnan(r[key]) and not math.isnan(r["grad_steps"]))
        c = colours[i % len(colours)]
        out.append(f'<polyline fill="none" stroke="{c}" stroke-width="1.5" points="{pts}"/>'
                   f'<text x="{w - pad}" y="{pad + 14 * i}" font-size="11" fill="{c}" '
                   f'text-anchor="end">{name}</text>')
    return "\n".join(out + ["</g>"]), (w, h)


def analyse():
    rng = random.Random(56)
    training, at_evals, races, series = [], [], [], {}
    for rivals, arm, seed, folder in runs():
        rows = over_training(folder, rng)
        for r in rows:
            training.append({"rivals": rivals, "arm": arm, "seed": seed, **r})
        if rows and arm.startswith("cmask"):
            series[f"{arm} s{seed}"] = rows
        for steps, ev in evaluations(folder).items():
            contexts = table2.read_csv(ev / "contexts.csv")
            races.append({"rivals": rivals, "arm": arm, "seed": seed, "env_steps": steps,
                          "told": "truth", **table2.split_values(contexts)})
            if (ev / "mask_episodes.csv").is_file():
                observed, shuffled, means = table2.mask_stats(
                    table2.read_csv(ev / "mask_episodes.csv"), rng, SHUFFLES)
                at_evals.append({"rivals": rivals, "arm": arm, "seed": seed, "env_steps": steps,
                                 **means, **{f"{k}_excess": observed[k] - shuffled[k]
                                             for k in observed}})
        # the final best policy's context ablation: told zeros or another context, fixed masks
        for told in sorted(p for p in (folder / "ablation").glob("*") if p.is_dir()):
            if (told / "contexts.csv").is_file():
                races.append({"rivals": rivals, "arm": arm, "seed": seed,
                              "env_steps": max(evaluations(folder), default=0),
                              "told": told.name,
                              **table2.split_values(table2.read_csv(told / "contexts.csv"))})
    if not training and not races:
        sys.exit(f"no runs under {HERE}/<R>r/<arm>/seed<S>/: run deploy/campaign.sh docs/long")
    verdicts = []
    for key in sorted({(r["rivals"], r["arm"], r["env_steps"]) for r in at_evals}):
        mine = [r for r in at_evals if (r["rivals"], r["arm"], r["env_steps"]) == key]
        for part in ["speed", "steer"]:
            xs = [r[f"mi_{part}_excess"] for r in mine]
            lo, hi = table2.student_mean(xs) if len(xs) > 1 else (float("nan"),) * 2
            m = table2.mean(xs)
            v = (f"not judged ({len(xs)} seed)" if len(xs) < 2 else
                 "context-dependent" if m > MARGIN_BITS and lo > 0 else
                 "not" if -MARGIN_BITS <= lo and hi <= MARGIN_BITS else "undecided")
            verdicts.append({"rivals": key[0], "arm": key[1], "env_steps": key[2],
                             "component": part, "seeds": len(xs), "mi_excess": m,
                             "t_lo": lo, "t_hi": hi, "verdict": v})
    for name, rows in [("mask_over_training.csv", training), ("mask_at_evaluations.csv",
                       at_evals + verdicts), ("races.csv", races)]:
        table2.write_csv(name, rows, HERE)
    md = ["# Long runs (written by `python3 docs/long/long.py analyse`)", "",
          "## M3: the mask SAC's temperature", ""]
    for name, rows in sorted(series.items()):
        md.append(f"- {name}: alpha below 0.5 from gradient step "
                  f"{first_below(rows, 'alpha', 0.5)}, below 0.2 from {first_below(rows, 'alpha', 0.2)}")
    md += ["", "## M1: does the mask depend on the context? (MI excess over the shuffled "
           "baseline, bits; mean over seeds, t interval)", "",
           "| rivals | arm | env steps | component | seeds | MI excess | t 95% | verdict |",
           "|--:|---|--:|---|--:|--:|---|---|"]
    for v in verdicts:
        md.append(f"| {v['rivals']} | {v['arm']} | {v['env_steps']} | {v['component']} | "
                  f"{v['seeds']} | {table2.fmt(v['mi_excess'], 4)} | "
                  f"[{table2.fmt(v['t_lo'], 4)}, {table2.fmt(v['t_hi'], 4)}] | {v['verdict']} |")
    md += ["", "## M4: the races at each evaluation (per seed; at the end also the context "
           "ablation: the agent told zeros or another episode's context, or its mask fixed)", "",
           "| rivals | arm | seed | env steps | context told | PG in | PG out | A2A in | A2A out |",
           "|--:|---|--:|--:|---|--:|--:|--:|--:|"]
    for r in races:
        md.append(f"| {r['rivals']} | {r['arm']} | {r['seed']} | {r['env_steps']} | "
                  f"{r['told']} | {table2.fmt(r['pg_in'])} | {table2.fmt(r['pg_out'])} | "
                  f"{table2.fmt(r['a2a_in'], 1)} | {table2.fmt(r['a2a_out'], 1)} |")
    (HERE / "results.md").write_text("\n".join(md) + "\n")
    panels = [svg(series, k, t) for k, t in
              [("alpha", "alpha"), ("entropy", "mask entropy (nats)"),
               ("mi_speed_excess", "MI(m_v; context) excess, bits"),
               ("mi_steer_excess", "MI(m_theta; context) excess, bits")]]
    panels = [p for p in panels if p]
    if panels:
        w, h = panels[0][1]
        body = "".join(f'<g transform="translate(0,{i * h})">{p[0]}</g>' for i, p in enumerate(panels))
        (HERE / "mask_over_training.svg").write_text(
            f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h * len(panels)}">'
            f'<rect width="100%" height="100%" fill="white"/>{body}</svg>\n')
    print((HERE / "results.md").read_text())


if __name__ == "__main__":
    if sys.argv[1:] == ["analyse"]:
        analyse()
    else:
        sys.exit(__doc__)
