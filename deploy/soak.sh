#!/usr/bin/env bash
# Soak test of the training runtime: trains a small SAC run with every process pinned to two
# cores, kills a random actor every 20 s, and at the end checks that every process is alive,
# that the replay's counts reconcile with what the actors report, and that memory did not grow
# after the warm-up (the replay buffer is small, so it is full by then).
#
# usage: deploy/soak.sh [SECONDS=120] [ACTORS=3]     (env CTXRACE_BIN: the binary to use,
#                                                     default target/debug/ctxrace)
set -euo pipefail
secs=${1:-120}
actors=${2:-3}
bin=$(realpath "${CTXRACE_BIN:-target/debug/ctxrace}")
dir=$(mktemp -d)
trap 'kill -TERM $launcher 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$dir"' EXIT

cat > "$dir/exp.toml" <<TOML
track = "generated:0"
[race]
rivals = 1
[agent]
algo = "sac"
[agent.sac]
hidden = 32
batch_size = 32
[train]
env_steps = 1000000000
prefill = 400
train_ratio = 0.25
policy_every = 20
checkpoint_every = 500
log_every = 100
threads = 1
[replay]
capacity = 20000
snapshot_every_secs = 10
[supervisor]
max_restarts = 1000   # the soak kills on purpose
TOML

run="$dir/run"
taskset -c 0,1 "$bin" train "$dir/exp.toml" --actors "$actors" --run-dir "$run" \
    2> "$dir/launcher.log" > /dev/null &
launcher=$!

# pids of the run's processes in a role (the role is the binary's first argument)
pids() {
    for p in /proc/[0-9]*; do
        cmd=$(tr '\0' ' ' < "$p/cmdline" 2>/dev/null) || continue
        case "$cmd" in *" $1 --run-dir $run "*) basename "$p" ;; esac
    done
}
rss_kib() {
    local total=0
    for role in replay learner actor; do
        for p in $(pids "$role"); do
            kib=$(awk '/VmRSS/ {print $2}' "/proc/$p/status" 2>/dev/null || echo 0)
            total=$((total + ${kib:-0}))
        done
    done
    echo "$total"
}

warmup=$(( secs < 60 ? secs / 3 : 30 ))
sleep "$warmup"
rss_start=$(rss_kib)
kills=0
elapsed=$warmup
while (( elapsed + 20 <= secs )); do
    sleep 20
    elapsed=$((elapsed + 20))
    victims=($(pids actor))
    if (( ${#victims[@]} > 0 )); then
        kill -9 "${victims[RANDOM % ${#victims[@]}]}"
        kills=$((kills + 1))
    fi
done
sleep 5   # let the launcher restart the last victim
rss_end=$(rss_kib)

fail=0
for role in replay learner; do
    [[ -n "$(pids $role)" ]] || { echo "soak: no $role alive"; fail=1; }
done
alive=$(pids actor | wc -l)
(( alive == actors )) || { echo "soak: $alive of $actors actors alive"; fail=1; }
if (( rss_end > rss_start * 13 / 10 + 20480 )); then
    echo "soak: memory grew from $rss_start KiB to $rss_end KiB"; fail=1
fi

kill -TERM "$launcher" 2>/dev/null || true
wait "$launcher" || { echo "soak: launcher failed"; fail=1; }
inserted=$(grep -o '"inserted": [0-9]*' "$run/replay-status.json" | grep -o '[0-9]*$')
rejected=$(grep -o '"rejected": [0-9]*' "$run/replay-status.json" | grep -o '[0-9]*$')
reported=$(cat "$run"/actors/*.json | grep -o '"sent_steps": [0-9]*' | grep -o '[0-9]*$' \
    | paste -sd+ | bc)
# killed actors cannot report, so the replay holds at least what the others delivered
(( inserted >= reported )) || { echo "soak: replay $inserted < reported $reported"; fail=1; }
(( rejected == 0 )) || { echo "soak: $rejected messages rejected"; fail=1; }
restarts=$(grep -c "exited" "$dir/launcher.log" || true)
echo "soak: ${secs}s, $actors actors, $kills kills, $restarts restarts, $inserted steps stored" \
    "($reported reported by clean exits), rss $rss_start -> $rss_end KiB"
if (( fail )); then
    echo "soak: launcher log:"; tail -20 "$dir/launcher.log"
fi
exit "$fail"
