#!/usr/bin/env bash
# deploy/paper_sac_bench.sh PAPER_GIT_DIR [CALLS]: times the paper's own PyTorch SAC update on CPU
# (ContextAwareF110/Utils/SAC.py of lilpharaoh1/context-f110, the SAC baseline of the paper's tables:
# 108 beams x 2 stacked frames, 2x100 ReLU, batch 100, lr 3e-5, gamma 0.85), on random transitions,
# with torch on 1 and on 2 threads. Each `train()` call of the paper's code makes 2 gradient steps
# (its 2 updates per env step); prints JSON {"sac_ms_1_thread": .., "sac_ms_2_threads": ..}, the
# median ms per gradient step, and the same without the time its buffer takes to sample a batch
# ("sac_sampling_ms_*", per gradient step: ctxrace samples in its replay process, not in the step),
# for comparison with `ctxrace bench learner --algo sac` in the same
# session (deploy/learner_vs_paper.sh runs both). Needs torch, numpy, matplotlib (the paper's module
# imports it).
set -euo pipefail
git_dir=${1:?usage: deploy/paper_sac_bench.sh PAPER_GIT_DIR [CALLS]}
calls=${2:-50}
work=$(mktemp -d); trap 'rm -rf "$work"' EXIT
git --git-dir="$git_dir" archive HEAD ContextAwareF110/Utils | tar -x -C "$work"
cat >"$work/bench.py" <<'PY'
import sys, time, numpy as np, torch
calls, threads = int(sys.argv[1]), int(sys.argv[2])
torch.set_num_threads(threads)
torch.manual_seed(0); np.random.seed(0)
from ContextAwareF110.Utils.SAC import SAC
beams, frames, act = 108, 2, 2
agent = SAC(beams, act, "bench", max_action=1, window_in=frames, window_out=1, lr=3e-5, gamma=0.85)
agent.create_agent(100)
rng = np.random.default_rng(0)
for i in range(5000):
    done = (i % 500) == 499
    agent.replay_buffer.add(rng.random(beams), rng.uniform(-1, 1, act), rng.normal(), done)
agent.train()  # warm-up
ts, samples = [], []
for _ in range(calls):
    t = time.perf_counter(); agent.train(); ts.append(time.perf_counter() - t)
    t = time.perf_counter(); agent.replay_buffer.sample(100); samples.append(time.perf_counter() - t)
# train() makes 2 gradient steps
tag = f'{threads}_thread{"s" if threads > 1 else ""}'
print(f'"sac_ms_{tag}": {1000 * float(np.median(ts)) / 2:.3f}, '
      f'"sac_sampling_ms_{tag}": {1000 * float(np.median(samples)):.3f}')
PY
cd "$work"
out=""
for threads in 1 2; do
  r=$(python3 bench.py "$calls" "$threads" 2>"$work/err" | grep "_ms_" | tail -n 1) || true
  if [ -n "$r" ]; then out="$out$r, "
  else tail -n 5 "$work/err" >&2; out="$out\"sac_error_$threads\": 1, "; fi
done
echo "{${out%, }}"
