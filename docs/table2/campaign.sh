#!/usr/bin/env bash
# Issue 55's runs in priority order, each trained, evaluated and collected into docs/table2 as
# it finishes: the 1-rival cells first (the table's 5 seeds of every arm, then seeds
# 10050-10090), then 3 rivals, then the low-temperature arm. A run whose record folder already
# keeps its checkpoints (`<R>r/<arm>/seed<S>/checkpoints`) is done and skipped, so the campaign
# continues across sessions from what is committed; an interrupted run resumes exactly from its
# sweep folder when that is still there. Runs are claimed (runs/.claims), so two campaigns may
# share the list.
#   docs/table2/campaign.sh            # JOBS=2 runs at a time, CTXRACE_BIN=target/release/ctxrace
set -euo pipefail
cd "${CTXRACE_REPO:-$(dirname "$0")/../..}"
BIN=${CTXRACE_BIN:-target/release/ctxrace}
JOBS=${JOBS:-2}
CONFIGS=${CTXRACE_CONFIGS:-configs/paper}

# matrix arm algo rivals seed, one per line, highest priority first
plan() {
    local s
    for s in 10000 10010 10020 10030 10040; do
        for a in dreamerv3 crssm cmask; do echo "table2 $a $a 1 $s"; done
        echo "table2-paper-mask cmask-paper-mask cmask 1 $s"
        echo "table2 sac sac 1 $s"
    done
    for s in 10050 10060 10070 10080 10090; do
        echo "table2-more-seeds dreamerv3 dreamerv3 1 $s"
        echo "table2-more-seeds crssm crssm 1 $s"
        echo "table2-more-seeds cmask cmask 1 $s"
        echo "table2-paper-mask cmask-paper-mask cmask 1 $s"
    done
    for s in 10000 10010 10020 10030 10040; do
        for a in sac dreamerv3 crssm cmask; do echo "table2 $a $a 3 $s"; done
        echo "table2-paper-mask cmask-paper-mask cmask 3 $s"
    done
    for s in 10000 10010 10020 10030 10040; do
        echo "table2-paper-mask-alpha0.05 cmask-paper-mask-alpha0.05 cmask 1 $s"
    done
}

one() {
    local matrix=$1 arm=$2 algo=$3 rivals=$4 seed=$5
    local name="$algo-f1_esp-${rivals}r-s$seed"
    if [[ -d docs/table2/${rivals}r/$arm/seed$seed/checkpoints ]]; then
        return 0
    fi
    # a run is claimed by one campaign (several may run at once, e.g. one per core)
    mkdir -p runs/.claims runs/logs
    mkdir "runs/.claims/$matrix-$name" 2> /dev/null || return 0
    echo "$(date -u +%FT%TZ) start $arm ${rivals}r s$seed"
    if "$BIN" sweep "$CONFIGS/$matrix.toml" --out "runs/$matrix" --cores 1 --run "$name" \
        > "runs/logs/$matrix-$name.log" 2>&1; then
        # one collect at a time: reproduction.csv is read and rewritten
        flock runs/.collect.lock python3 docs/table2/table2.py collect "runs/$matrix" "$arm" \
            "$name"
        echo "$(date -u +%FT%TZ) done $arm ${rivals}r s$seed"
    else
        echo "$(date -u +%FT%TZ) FAILED $arm ${rivals}r s$seed: see runs/logs/$matrix-$name.log"
    fi
    rmdir "runs/.claims/$matrix-$name"
}
export -f one
export BIN CONFIGS
plan | xargs -P "$JOBS" -L 1 bash -c 'one "$@"' _
