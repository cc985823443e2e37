#!/usr/bin/env bash
# deploy/paper_crssm_bench.sh PAPER_GIT_DIR [STEPS]: times the paper's own PyTorch cRSSM training
# step on CPU, 2 threads (ContextAwareF110/Utils/cdreamer of lilpharaoh1/context-f110: the agent
# its training-progress plots label "cRSSM", a DreamerV3 whose RSSM and heads take the context,
# `add_dcontext`), with its config (batch 16 x 64, 108 beams, lr 3e-5), on synthetic episodes
# that carry a context, as ../shared/tools/paper_learner_bench.sh does for DreamerV3 and cMask.
# Prints JSON {"crssm_ms": ..}, the median ms per step, for comparison with
# `ctxrace bench learner --algo crssm` in the same session (deploy/learner_vs_paper.sh runs both).
# Needs torch, numpy, pyyaml and gym.
set -euo pipefail
git_dir=${1:?usage: deploy/paper_crssm_bench.sh PAPER_GIT_DIR [STEPS]}
steps=${2:-4}
work=$(mktemp -d); trap 'rm -rf "$work"' EXIT
git --git-dir="$git_dir" archive HEAD ContextAwareF110 | tar -x -C "$work"
agent="$work/ContextAwareF110/Utils/cdreamer"
sed -i -e "s/device: 'cuda:0'/device: 'cpu'/" -e "s/compile: True/compile: False/" "$agent/configs.yaml"
# the networks' hard-coded CUDA defaults
sed -i -e "s/'cuda:0'/'cpu'/g" -e 's/"cuda:0"/"cpu"/g' -e "s/'cuda'/'cpu'/g" -e 's/"cuda"/"cpu"/g' \
  "$agent/"*.py
cat >"$work/bench.py" <<'PY'
import sys, time, pathlib, numpy as np, torch
torch.set_num_threads(2)
steps = int(sys.argv[1])
# cdreamer's modules first; its exploration module imports `models`, which lives beside
# dreamerv3's
utils = pathlib.Path("ContextAwareF110/Utils").resolve()
sys.path.insert(0, str(utils / "cdreamer"))
sys.path.append(str(utils / "dreamerv3"))
from ContextAwareF110.Utils.cdreamer.dreamerv3 import DreamerV3
a = DreamerV3(108, 2, "bench", max_action=1, window_in=1, window_out=1, lr=3e-5)
rng = np.random.default_rng(0)
for e in range(40):
    T = 120
    a.buffer_eps[f"eps_{e}"] = {
        "is_first": np.r_[1.0, np.zeros(T - 1)].reshape(T, 1), "image": rng.random((T, 108)),
        "action": rng.uniform(-1, 1, (T, 2)), "reward": rng.normal(size=(T, 1)),
        "is_terminal": np.zeros((T, 1)),
        "context": np.tile(rng.uniform(-0.15, 0.15, (1, 2)), (T, 1))}
a.train()  # warm-up
ts = []
for _ in range(steps):
    t = time.perf_counter(); a.train(); ts.append(time.perf_counter() - t)
print(f'"crssm_ms": {1000 * float(np.median(ts)):.1f}')
PY
cd "$work"
r=$(python3 bench.py "$steps" 2>"$work/err" | grep "_ms\"" | tail -n 1) || true
if [ -z "$r" ]; then tail -n 5 "$work/err" >&2; r='"crssm_error": 1'; fi
echo "{$r}"
