#!/usr/bin/env bash
# Soak test of the training runtime: trains a small SAC run with every process pinned to two
# cores, kills a random process every 20 s (an actor; with VICTIMS=all an actor, the learner or
# the replay), and at the end checks that every process is alive, that the replay's counts
# reconcile with what the actors report, that nothing was rejected, and that memory did not
# grow after the warm-up (the replay buffer is small, so it is full by then). It prints the
# kills and restarts, the steps sent and stored, the rejections by reason, the replay's longest
# stall and each actor's share of the steps.
#
# usage: deploy/soak.sh [SECONDS=120] [ACTORS=3] [VICTIMS=actors|all]
#        (env CTXRACE_BIN: the binary to use, default target/release/ctxrace)
set -euo pipefail
secs=${1:-120}
actors=${2:-3}
victims_of=${3:-actors}
case "$victims_of" in actors|all) ;; *) echo "soak: VICTIMS must be actors or all" >&2; exit 2 ;; esac
bin=$(realpath "${CTXRACE_BIN:-target/release/ctxrace}")
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
max_restarts = 1000   # the soak kills on purpose, every 20 s:
restart_window_secs = 30   # a back-off of 1 s, not one grown over the whole soak
TOML

run="$dir/run"
taskset -c 0,1 "$bin" train "$dir/exp.toml" --actors "$actors" --run-dir "$run" \
    2> "$dir/launcher.log" > /dev/null &
launcher=$!

# pids of the run's processes in a role (the role is the binary's first argument)
pids() {
    for p in /proc/[0-9]*; do
        cmd=$({ tr '\0' ' ' < "$p/cmdline"; } 2>/dev/null) || continue
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
declare -A killed=([actor]=0 [learner]=0 [replay]=0)
elapsed=$warmup
while (( elapsed + 20 <= secs )); do
    sleep 20
    elapsed=$((elapsed + 20))
    role=actor
    if [[ $victims_of == all ]]; then
        roles=(actor actor learner replay)
        role=${roles[RANDOM % 4]}
    fi
    victims=($(pids "$role"))
    if (( ${#victims[@]} > 0 )); then
        kill -9 "${victims[RANDOM % ${#victims[@]}]}"
        kills=$((kills + 1))
        killed[$role]=$((${killed[$role]} + 1))
    fi
done
# let the launcher restart the last victims (its back-off reaches 30 s after repeated kills)
for _ in $(seq 60); do
    [[ -n "$(pids replay)" && -n "$(pids learner)" ]] && (( $(pids actor | wc -l) == actors )) \
        && break
    sleep 1
done
sleep 2
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
if [[ ! -f "$run/replay-status.json" ]]; then
    echo "soak: the replay wrote no final status"; tail -20 "$dir/launcher.log"; exit 1
fi
inserted=$(grep -o '"inserted": [0-9]*' "$run/replay-status.json" | grep -o '[0-9]*$')
rejected=$(grep -o '"rejected": [0-9]*' "$run/replay-status.json" | grep -o '[0-9]*$')
reported=$(cat "$run"/actors/*.json | grep -o '"sent_steps": [0-9]*' | grep -o '[0-9]*$' \
    | paste -sd+ | bc)
# killed actors cannot report, so the replay holds at least what the others delivered (a
# killed replay loses what came after its last snapshot: then this is only reported)
if (( ${killed[replay]} == 0 )); then
    (( inserted >= reported )) || { echo "soak: replay $inserted < reported $reported"; fail=1; }
fi
(( rejected == 0 )) || { echo "soak: $rejected messages rejected"; fail=1; }
restarts=$(grep -c "exited" "$dir/launcher.log" || true)
stall=$(grep -o '"longest_turn_ms": [0-9.e+-]*' "$run/replay-status.json" | grep -o '[0-9.e+-]*$')
reasons=$(tr -d ' \n' < "$run/replay-status.json" | grep -o '"rejected_by_reason":{[^}]*}' || true)
# each actor's share of the steps run, from the launcher's episode log (actor is column 3)
shares=$(awk -F, 'NR > 1 { s[$3] += $NF; t += $NF } END {
    for (a in s) printf "actor %s %.3f  ", a, s[a] / t }' "$run/episodes.csv")
echo "soak: ${secs}s, $actors actors, $kills kills (actors ${killed[actor]}, learner" \
    "${killed[learner]}, replay ${killed[replay]}), $restarts restarts, $inserted steps stored" \
    "($reported reported by clean exits), rejected $rejected ${reasons:-}, longest replay stall" \
    "${stall:-?} ms (its last start), shares: $shares, rss $rss_start -> $rss_end KiB"
if (( fail )); then
    echo "soak: launcher log:"; tail -20 "$dir/launcher.log"
fi
exit "$fail"
