#!/usr/bin/env bash
# deploy/campaign.sh RECORDS: the runs of RECORDS/plan.txt in its order, each trained, evaluated
# and collected into RECORDS/<R>r/<arm>/seed<S>/ (docs/table2/table2.py collect) as it finishes,
# JOBS at a time. A plan line is `matrix arm algo rivals seed` (matrix: a file of
# configs/paper without .toml). A run whose record folder keeps its checkpoints is done and
# skipped, so a campaign continues across sessions from what is committed; an interrupted run
# continues exactly from its sweep folder (runs/<matrix>/) when that is still there. Runs are
# claimed (runs/.claims), so two campaigns may share a plan. A run that kept best policies on
# the way (`[train] keep_best_at`) has each evaluated on the matrix's grid, KEPT_LAPS laps a
# context, into <run>/eval-at-<N>/ before it is collected.
#   deploy/campaign.sh docs/table2      # issue 55's table; docs/long: issue 56's long runs
# A run in flight can be archived as RECORDS/inflight/<run>.tar.gz (ignored by git: a run folder
# is generated output) to carry it to a machine or checkout without its runs/:
#   deploy/campaign.sh docs/long --stash   # after stopping the campaign: each unfinished run's
#                                          # folder at its resume point
# and a campaign restores it before resuming the run; collecting the run deletes it.
# Environment: JOBS [2]; CTXRACE_BIN [target/release/ctxrace]; CTXRACE_CONFIGS [configs/paper];
# KEPT_LAPS [20]; CTXRACE_REPO: the repository [this script's].
set -euo pipefail
cd "${CTXRACE_REPO:-$(dirname "$0")/..}"
RECORDS=${1:?usage: deploy/campaign.sh RECORDS [--stash] (a folder holding plan.txt)}
BIN=${CTXRACE_BIN:-target/release/ctxrace}
JOBS=${JOBS:-2}
CONFIGS=${CTXRACE_CONFIGS:-configs/paper}
KEPT_LAPS=${KEPT_LAPS:-20}

one() {
    local matrix=$1 arm=$2 algo=$3 rivals=$4 seed=$5
    local name="$algo-f1_esp-${rivals}r-s$seed" run="runs/$matrix/$algo-f1_esp-${rivals}r-s$seed"
    if [[ -d $RECORDS/${rivals}r/$arm/seed$seed/checkpoints ]]; then
        return 0
    fi
    mkdir -p runs/.claims runs/logs
    mkdir "runs/.claims/$matrix-$name" 2> /dev/null || return 0
    local log="runs/logs/$matrix-$name.log" stashed="$RECORDS/inflight/$matrix-$name.tar.gz"
    if [[ ! -d $run && -f $stashed ]]; then
        tar -xzf "$stashed" && echo "$(date -u +%FT%TZ) restored $stashed"
    fi
    echo "$(date -u +%FT%TZ) start $arm ${rivals}r s$seed"
    # one collect at a time: reproduction.csv is read and rewritten
    if "$BIN" sweep "$CONFIGS/$matrix.toml" --out "runs/$matrix" --cores 1 --run "$name" \
        > "$log" 2>&1 && kept_evals "$run" >> "$log" 2>&1 \
        && flock runs/.collect.lock python3 docs/table2/table2.py collect "runs/$matrix" \
            "$arm" "$name" --into "$RECORDS" >> "$log" 2>&1; then
        rm -f "$stashed"
        echo "$(date -u +%FT%TZ) done $arm ${rivals}r s$seed"
    else
        echo "$(date -u +%FT%TZ) FAILED $arm ${rivals}r s$seed: see $log"
    fi
    rmdir "runs/.claims/$matrix-$name"
}

# each best policy the run kept on the way, evaluated as its main evaluation but for the laps
kept_evals() {
    local run=$1 kept meta
    meta="$run/eval/meta.json"
    for kept in "$run"/checkpoints/best-at-*; do
        [[ -d $kept ]] || continue
        "$BIN" eval "$run" --checkpoint "$(basename "$kept")" --laps "$KEPT_LAPS" \
            --grid "$(json_key "$meta" grid)" --range "$(json_key "$meta" range)" \
            --act "$(json_key "$meta" act)" --seed "$(json_key "$meta" seed)" --out "$run/eval-at-${kept##*best-at-}" --workers 1
    done
}

json_key() { python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' "$@"; }

# each planned run that is not collected and has a resume point, archived for a fresh checkout
stash() {
    local matrix=$1 arm=$2 algo=$3 rivals=$4 seed=$5
    local name="$algo-f1_esp-${rivals}r-s$seed"
    local run="runs/$matrix/$name"
    if [[ -d $RECORDS/${rivals}r/$arm/seed$seed/checkpoints || ! -d $run/resume ]]; then
        return 0
    fi
    mkdir -p "$RECORDS/inflight"
    tar -czf "$RECORDS/inflight/$matrix-$name.tar.gz" "$run" "runs/$matrix/configs/$name.toml"
    echo "stashed $run: $(du -h "$RECORDS/inflight/$matrix-$name.tar.gz" | cut -f1)"
}

export -f one kept_evals json_key
if [[ ${2:-} == --stash ]]; then
    grep -v '^#' "$RECORDS/plan.txt" | grep . | while read -r line; do
        # shellcheck disable=SC2086  # a plan line's fields
        stash $line
    done
    exit 0
fi
export BIN CONFIGS RECORDS KEPT_LAPS
grep -v '^#' "$RECORDS/plan.txt" | grep . | xargs -P "$JOBS" -L 1 bash -c 'one "$@"' _
