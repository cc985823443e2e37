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
set -euo pipefail
cd "$(dirname "$0")/.."
git_dir=${1:?usage: deploy/learner_vs_paper.sh PAPER_GIT_DIR [ROUNDS]}
rounds=${2:-3}
bin=${CTXRACE_BIN:-target/release/ctxrace}
harness=../shared/tools/paper_learner_bench.sh
[[ -x "$bin" ]] || { echo "no $bin: build it with cargo build --release" >&2; exit 1; }
[[ -f "$harness" ]] || { echo "no $harness: the paper's harness lives in ../shared/tools" >&2; exit 1; }
path=${PYTHON_BIN_DIR:+$PYTHON_BIN_DIR:}$PATH
for ((round = 1; round <= rounds; round++)); do
    for algo in dreamerv3 crssm cmask sac; do
        echo "ctxrace round $round $algo:"
        "$bin" bench learner --algo "$algo" --steps 5 --act-steps 200
    done
    if ((round < rounds)); then
        echo "paper round $round: $(PATH=$path bash "$harness" "$git_dir" 4 | tail -1)"
        echo "paper cRSSM round $round: $(PATH=$path deploy/paper_crssm_bench.sh "$git_dir" 4 | tail -1)"
        echo "paper SAC round $round: $(PATH=$path deploy/paper_sac_bench.sh "$git_dir" 50 | tail -1)"
    fi
done
