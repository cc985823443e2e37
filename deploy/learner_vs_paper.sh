#!/usr/bin/env bash
# deploy/learner_vs_paper.sh PAPER_GIT_DIR [ROUNDS]: ctxrace's learner and the paper's PyTorch
# learner alternately on this machine (ctxrace, paper, ctxrace, ..., ctxrace: ROUNDS ctxrace runs,
# default 3), every figure printed, so that the ratio comes from one session on one machine.
#   PAPER_GIT_DIR: a git directory of lilpharaoh1/context-f110 (e.g. from the library's `fetch`)
#   env CTXRACE_BIN: the binary (default target/release/ctxrace); PYTHON_BIN_DIR: a folder whose
#   python has torch, numpy, pyyaml and gym (default: the one on PATH)
# The paper's side is ../shared/tools/paper_learner_bench.sh (DreamerV3 and cMask, 2 threads),
# deploy/paper_crssm_bench.sh (its cRSSM, 2 threads) and deploy/paper_sac_bench.sh (its SAC
# baseline; python also needs matplotlib).
# AVX2 on an AVX-512 machine: CTXRACE_BIN from `cargo build --release -p ctxrace
# --no-default-features --target-dir target/avx2`, and torch capped with ATEN_CPU_CAPABILITY=avx2
# MKL_ENABLE_INSTRUCTIONS=AVX2 ONEDNN_MAX_CPU_ISA=AVX2 in the environment.
# At the end it prints a table: each side's median per gradient step in every round, and the
# range and median of the ratios of each paper round to the ctxrace rounds on either side of it
# (the paper's SAC: the faster of its 1- and 2-thread figures less its buffer's sampling time,
# which ctxrace spends in the replay process), and the share of the CPUs' time the hypervisor
# took (steal time, /proc/stat) during each side's rounds: on a shared virtual machine the
# paper's code, whose threads meet at every operation, slows more than ctxrace when it is high.
# `deploy/learner_vs_paper.sh --table LOG` prints the table of a saved run's output.
set -euo pipefail
cd "$(dirname "$0")/.."
path=${PYTHON_BIN_DIR:+$PYTHON_BIN_DIR:}$PATH

# table LOG: the medians and ratios of a run's output
table() {
    [[ -f $1 ]] || { echo "no file $1: --table reads the saved output of this script" >&2; exit 1; }
    PATH=$path python3 - "$1" <<'PY'
import json, re, sys
algos = ["dreamerv3", "crssm", "cmask", "sac"]
ours, paper = {a: [] for a in algos}, {a: [] for a in algos}
steal = []
for number, line in enumerate(open(sys.argv[1]), 1):
    m = re.match(r"steal (ctxrace|paper) round \d+: ([0-9.]+)%", line)
    if m:
        steal.append(m.group(2))
        continue
    m = re.match(r"(dreamerv3|crssm|cmask|sac) \(.*median ([0-9.]+) ms\)", line)
    if m:
        ours[m.group(1)].append(float(m.group(2)))
        continue
    m = re.match(r"paper (round|cRSSM round|SAC round) \d+: (.*)$", line)
    if not m:
        continue
    try:
        d = json.loads(m.group(2))
    except json.JSONDecodeError as e:
        sys.exit(f"{sys.argv[1]}:{number}: the paper's figures are not JSON ({e}): is the log cut?")
    if "dreamerv3_ms" in d:
        paper["dreamerv3"].append(d["dreamerv3_ms"])
        paper["cmask"].append(d["cmask_ms"])
    if "crssm_ms" in d:
        paper["crssm"].append(d["crssm_ms"])
    if "sac_ms_1_thread" in d:
        paper["sac"].append(min(d[f"sac_ms_{t}"] - d[f"sac_sampling_ms_{t}"]
                                for t in ("1_thread", "2_threads")))
if not any(ours.values()) and not any(paper.values()):
    sys.exit(f"{sys.argv[1]}: no figures of ctxrace or the paper: not this script's output?")
print("| ms per gradient step | ctxrace and paper rounds, alternately | paper / ctxrace, all pairs |")
print("|---|---|---|")
for a in algos:
    c, p = ours[a], paper[a]
    cells = [f"{v:.4g}" for pair in zip(c, p + [None]) for v in pair if v is not None]
    ratios = [pv / c[j] for i, pv in enumerate(p) for j in (i, i + 1) if j < len(c)]
    ratios.sort()
    middle = (ratios[(len(ratios) - 1) // 2] + ratios[len(ratios) // 2]) / 2 if ratios else 0
    span = f"{ratios[0]:.1f}-{ratios[-1]:.1f}x (median {middle:.2f}x)" if ratios else "no pairs"
    print(f"| {a} | {' / '.join(cells)} | {span} |")
if steal:
    print(f"| steal time, % of the CPUs' | {' / '.join(steal)} | |")
PY
}
if [[ ${1:-} == --table ]]; then
    table "${2:?usage: deploy/learner_vs_paper.sh --table LOG}"
    exit
fi
git_dir=${1:?usage: deploy/learner_vs_paper.sh PAPER_GIT_DIR [ROUNDS]}
rounds=${2:-3}
bin=${CTXRACE_BIN:-target/release/ctxrace}
harness=../shared/tools/paper_learner_bench.sh
[[ -x "$bin" ]] || { echo "no $bin: build it with cargo build --release" >&2; exit 1; }
[[ -f "$harness" ]] || { echo "no $harness: the paper's harness lives in ../shared/tools" >&2; exit 1; }
# cpu_times: the jiffies the hypervisor stole from all CPUs so far, and all their jiffies
# (Linux's /proc/stat; without it no steal line is printed rather than a made-up 0%)
cpu_times() {
    awk '/^cpu /{t = 0; for (i = 2; i <= 9; i++) t += $i; print $9, t}' /proc/stat
}
# steal_line WHO ROUND "STEAL TOTAL": the percentage of the CPUs' time stolen since cpu_times
# gave STEAL TOTAL, as a line of the log
steal_line() {
    [[ -r /proc/stat ]] || return 0
    local s0 t0 s1 t1
    read -r s0 t0 <<<"$3"
    read -r s1 t1 < <(cpu_times)
    awk -v d=$((s1 - s0)) -v t=$((t1 - t0)) -v who="$1" -v round="$2" \
        'BEGIN {printf "steal %s round %s: %.1f%%\n", who, round, (t > 0 ? 100 * d / t : 0)}'
}
log=$(mktemp); trap 'rm -f "$log"' EXIT
for ((round = 1; round <= rounds; round++)); do
    since=$(cpu_times 2>/dev/null || true)
    for algo in dreamerv3 crssm cmask sac; do
        echo "ctxrace round $round $algo:"
        "$bin" bench learner --algo "$algo" --steps 5 --act-steps 200
    done
    steal_line ctxrace "$round" "$since"
    if ((round < rounds)); then
        since=$(cpu_times 2>/dev/null || true)
        echo "paper round $round: $(PATH=$path bash "$harness" "$git_dir" 4 | tail -1)"
        echo "paper cRSSM round $round: $(PATH=$path deploy/paper_crssm_bench.sh "$git_dir" 4 | tail -1)"
        echo "paper SAC round $round: $(PATH=$path deploy/paper_sac_bench.sh "$git_dir" 50 | tail -1)"
        steal_line paper "$round" "$since"
    fi
done | tee "$log"
echo
table "$log"
