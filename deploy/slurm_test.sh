#!/usr/bin/env bash
# Integration test of `ctxrace sweep --emit slurm` on a real (one-node) Slurm cluster: starts one
# on this machine (deploy/slurm-one-node.sh, as root), emits the script of a tiny matrix (two SAC
# runs of 24,000 env steps on a generated track), submits it from another folder with
# --export=NONE, kills one array task once its run has a checkpoint, checks that the report job
# waits for the array, submits the script again and checks that the killed run resumed (its
# replay restored from the snapshot), that the finished one was not trained again, and that
# every run has its evaluation and the report was written. About a minute on 2 cores.
#
#   CTXRACE_BIN=target/release/ctxrace deploy/slurm_test.sh
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
bin=$(realpath "${CTXRACE_BIN:-$repo/target/release/ctxrace}")
[[ -x $bin ]] || { echo "slurm_test: no ctxrace binary at $bin (cargo build --release)" >&2; exit 1; }
started=$SECONDS
work=$(mktemp -d /tmp/ctxrace-slurm-test.XXXXXX)
state=$work/cluster
export SLURM_CONF=$state/slurm.conf

fail() {
    echo "slurm_test: FAILED: $*" >&2
    for f in "$work"/out/slurm/*.out "$work"/out/*/logs/*.log; do
        [[ -f $f ]] && { echo "--- $f" >&2; tail -n 15 "$f" >&2; }
    done
    exit 1
}
jobs=()
cleanup() {
    ((${#jobs[@]} == 0)) || scancel "${jobs[@]}" >/dev/null 2>&1 || true
    "$repo/deploy/slurm-one-node.sh" stop "$state" >/dev/null 2>&1 || true
    rm -rf "$work"
}
trap cleanup EXIT

# waits (at most $2 seconds) until the command $1 succeeds
wait_until() {
    local deadline=$((SECONDS + $2))
    until eval "$1"; do
        ((SECONDS < deadline)) || fail "timed out after $2 s waiting for: $1"
        sleep 0.5
    done
}
# whether job $1 (an array or a job) has left the queue
gone() { [[ -z $(squeue -h -j "$1" 2>/dev/null) ]]; }

"$repo/deploy/slurm-one-node.sh" start "$state"

cat >"$work/base.toml" <<'TOML'
track = "generated:0"
[race]
rivals = 1
max_time = 10.0
[agent]
algo = "sac"
[agent.sac]
hidden = 32
batch_size = 32
[train]
env_steps = 24000
prefill = 400
train_ratio = 0.25
policy_every = 10
checkpoint_every = 100
log_every = 50
[replay]
snapshot_every_secs = 1
TOML
cat >"$work/m.toml" <<'TOML'
base = "base.toml"
algos = ["sac"]
tracks = ["generated:0"]
rivals = [1]
seeds = [0, 1]
[train]
actors = 1
[eval]
grid = 2
range = 0.1
laps = 1
checkpoint = "latest"
TOML
mkdir -p "$work/tracks" "$work/elsewhere"
# emitted with relative paths; the script must name them absolutely
(cd "$work" && "$bin" sweep m.toml --out out --cores 1 --tracks-dir tracks --time 0:10:00 \
    --throttle 2 --emit slurm >submit.sh)
grep -q -- "--tracks-dir $work/tracks" "$work/submit.sh" || fail "the tracks folder is not pinned"
grep -q -- "#SBATCH --output=$work/out/slurm/%a.out" "$work/submit.sh" || fail "log path not absolute"

submit() {
    # from another folder, with nothing of this shell's environment but what sbatch needs
    (cd "$work/elsewhere" && env -i PATH="$PATH" SLURM_CONF="$SLURM_CONF" \
        bash "$work/submit.sh" --export=NONE)
}
line=$(submit) || fail "submission failed: $line"
echo "slurm_test: $line"
array=$(sed -E 's/.*array job ([0-9]+).*/\1/' <<<"$line")
report=$(sed -E 's/.*report job ([0-9]+).*/\1/' <<<"$line")
jobs+=("$array" "$report")
run0=$work/out/sac-generated_0-1r-s0
run1=$work/out/sac-generated_0-1r-s1

# kill every process of task 0 outright (SIGKILL: no checkpoint or snapshot on the way out)
# once its run has a checkpoint and a replay snapshot
wait_until "compgen -G '$run0/checkpoints/step-*' >/dev/null && [[ -f $run0/replay.snapshot ]]" 180
task0=$(squeue -h -j "${array}_0" -o %A)
pids=$(scontrol listpids "$task0" | awk 'NR > 1 && $1 ~ /^[0-9]+$/ { print $1 }')
[[ -n $pids ]] || fail "no process of task ${array}_0 (job $task0) found"
# shellcheck disable=SC2086 # one pid per word
kill -9 $pids 2>/dev/null || true
newest=$(basename "$(ls -d "$run0"/checkpoints/step-* | sort -V | tail -1)")
# the run's last checkpoint is step 5900 ((24000 - 400) x 0.25): the kill must come before it
((10#${newest#step-} < 5900)) || fail "task ${array}_0 finished training before the kill" \
    "($newest); raise env_steps in this script's base.toml"
echo "slurm_test: killed task ${array}_0 (kill -9 of its $(wc -w <<<"$pids") processes) past $newest"
wait_until "gone $array" 300
[[ -f $run1/eval/contexts.csv ]] || fail "task 1 did not evaluate its run"
[[ ! -f $run0/eval/contexts.csv ]] || fail "the killed task's run was evaluated"
# the report job waits for the array, and never starts once a task failed
wait_until "[[ \$(squeue -h -j $report -o %r) == DependencyNeverSatisfied ]]" 60
echo "slurm_test: report job $report held: DependencyNeverSatisfied"
scancel "$report"

line=$(submit) || fail "resubmission failed: $line"
echo "slurm_test: resubmitted: $line"
array=$(sed -E 's/.*array job ([0-9]+).*/\1/' <<<"$line")
report=$(sed -E 's/.*report job ([0-9]+).*/\1/' <<<"$line")
jobs+=("$array" "$report")
wait_until "gone $report || [[ \$(squeue -h -j $report -o %r) == DependencyNeverSatisfied ]]" 300
gone "$report" || fail "a task of the resubmitted array failed"
restored=$(grep -o '"restored_inserts": *[0-9]*' "$run0/replay-status.json" | grep -o '[0-9]*$')
((restored > 0)) || fail "the killed run did not resume from its replay snapshot"
resumed=$(sed -nE 's/.*learner resumed from .* at step ([0-9]+).*/\1/p' "$run0/logs/learner.log" | tail -1)
((${resumed:-0} > 0)) || fail "the killed run's learner did not resume from its checkpoint"
grep -q "is trained already" "$work/out/slurm/1.out" || fail "task 1 trained its finished run again"
for run in "$run0" "$run1"; do
    [[ -f $run/eval/contexts.csv ]] || fail "$(basename "$run") has no evaluation"
done
grep -q "2 runs evaluated" "$work/out/slurm/report.out" || fail "the report job did not report"
[[ -n $(ls "$work/out/report") ]] || fail "the report folder is empty"
echo "slurm_test: task 0 resumed its run (learner from step $resumed, $restored replay steps" \
    "restored): $(grep '^steps:' "$work/out/slurm/0.out" | tail -1)"
echo "slurm_test: task 1 ended at once: $(grep 'trained already' "$work/out/slurm/1.out")"
echo "slurm_test: report: $(ls "$work/out/report" | tr '\n' ' ')"
echo "slurm_test: passed in $((SECONDS - started)) s"
