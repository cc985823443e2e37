#!/usr/bin/env bash
# deploy/paper_sim_agreement.sh: the same race in both simulators (issue 45 item 2). The
# reference egos pure-pursuit, random and still race CONTEXTS of the 7 x 7 grid over +-0.3
# (c_v-major; the paper's test contexts 17-48, as the code's test loop, by default) on f1_esp
# against RIVALS rivals, in ctxrace under a paper-code race and in the paper's own simulator
# (lilpharaoh1/context-f110 at c0fd903: its F110Env, its TestSimulation loop, its PurePursuit
# rivals; the ego driven by deploy/paper_sim_agreement.py, which documents what the harness adds).
#
#   deploy/paper_sim_agreement.sh setup            a light Python environment for the paper's
#                                                   simulator (numpy, numba, scipy, ...; no torch)
#   deploy/paper_sim_agreement.sh paper [EGO..]    the paper's simulator -> DIR/paper_<ego>.csv
#   deploy/paper_sim_agreement.sh ctxrace VARIANT CONFIG [EGO..]
#                                                   `ctxrace eval` with the race of CONFIG (a race
#                                                   scenario TOML) -> DIR/ctxrace-VARIANT/<ego>/
#   deploy/paper_sim_agreement.sh table VARIANT    RAW's records, every rival count ->
#                                                   docs/table2/sim_agreement.csv (the ctxrace
#                                                   rows from ctxrace-VARIANT)
#   deploy/paper_sim_agreement.sh compare VARIANT..  DIR's per-ego summary, in and out of
#                                                   distribution, with 95% intervals, and the
#                                                   contexts that differ (markdown, to stdout)
#   deploy/paper_sim_agreement.sh all              setup, paper, both ctxrace variants, table,
#                                                   compare: what docs/table2/sim_agreement.md shows
# EGO: pure-pursuit, random, still [all three].
#
# Environment:
#   PAPER_GIT     git directory or clone address of lilpharaoh1/context-f110 (required by
#                 `paper`; e.g. the library's mirror)
#   PAPER_COMMIT  [c0fd903]; PAPER_WORK: where the commit is exported [/work/sim-paper]; it is
#                 exported unmodified (the harness writes its run file and records there)
#   SIM_VENV      the Python environment made by `setup`, outside the repo [/work/venv-sim]
#   RAW           raw records [docs/table2/sim_agreement]; DIR, the records of RIVALS rivals: RAW
#                 for 1, RAW/<RIVALS>r otherwise
#   PAPER_LAPS    laps per context in the paper's simulator [20]
#   PAPER_TAG     `paper` writes DIR/paper_<ego>.<tag>.csv instead (a further run; `table` and
#                 `compare` take each context from the run with the most laps of it)
#   CTXRACE_LAPS  laps per context in ctxrace [50]
#   CONTEXTS      grid indices raced on both sides, as `ctxrace eval --contexts` takes them
#                 (`0-48`: all) [17-48]
#   RIVALS        [1]; SEED: the random ego's seed [0]; CTXRACE_BIN [target/release/ctxrace]
#
# The ctxrace variants of `all`: `paper-code`, configs/scenarios/paper-code.toml (the preset
# with the fixes of docs/table2/sim_agreement.md), and `table-era`,
# configs/scenarios/paper-code-table-era.toml (the race the reduced Table II was trained and
# evaluated in: the preset as it was before the fixes, pinned).
#
# Measured on the project's 2-core machine at nice 10 beside a training run and other builds
# (load 9-10, 2026-12-06): `setup` about 1 min; `paper` at 20 laps a context pure-pursuit
# 64 min, random 15 min, still about 12 s a lap (2 h for all 640: docs/table2/sim_agreement.md
# says what ran); `ctxrace` 10-30 s per ego and variant. At load 3-5 (2026-12-07): `paper`
# pure-pursuit against 3 rivals on all 49 contexts at 5 laps a context 8.5-9.5 min.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=${SIM_VENV:-/work/venv-sim}
work=${PAPER_WORK:-/work/sim-paper}
commit=${PAPER_COMMIT:-c0fd903}
raw=${RAW:-docs/table2/sim_agreement}
rivals=${RIVALS:-1}
dir=$raw
((rivals == 1)) || dir=$raw/${rivals}r
contexts=${CONTEXTS:-17-48}
bin=${CTXRACE_BIN:-target/release/ctxrace}
egos_or_all() { if (($#)); then echo "$@"; else echo pure-pursuit random still; fi; }

setup() {
    if [[ -x $venv/bin/python ]] && "$venv/bin/python" -c 'import numpy, numba, scipy, yaml, gym, PIL, matplotlib, pyglet' 2>/dev/null; then
        echo "$venv: ready"
        return
    fi
    python3 -m venv "$venv"
    "$venv/bin/pip" install -q numpy numba scipy pyyaml 'gym==0.26.2' pillow matplotlib 'pyglet<1.6'
    echo "$venv: installed"
}

export_paper() {
    local git_dir=${PAPER_GIT:?set PAPER_GIT to a git directory or clone address of lilpharaoh1/context-f110}
    if [[ -f $work/TrajectoryAidedLearning/TestSimulation.py ]]; then
        return
    fi
    mkdir -p "$work"
    if [[ ! -d $git_dir ]]; then
        git clone --quiet --bare "$git_dir" "$work/.paper.git"
        git_dir=$work/.paper.git
    fi
    git --git-dir="$git_dir" archive "$commit" | tar -x -C "$work"
}

paper() {
    export_paper
    mkdir -p "$dir"
    local ego start out
    for ego in $(egos_or_all "$@"); do
        start=$(date +%s)
        out=$dir/paper_$ego${PAPER_TAG:+.$PAPER_TAG}.csv
        rm -rf "$work/Data/Vehicles/sim_agreement"
        nice -n 10 "$venv/bin/python" deploy/paper_sim_agreement.py "$work" "$ego" "$out" \
            --laps "${PAPER_LAPS:-20}" --rivals "$rivals" --contexts "$contexts" \
            --seed "${SEED:-0}" >"$work/sim_agreement_$ego.log"
        echo "paper $ego: $out ($(($(date +%s) - start)) s)"
    done
}

ctxrace_side() {
    local variant=${1:?give the variant name} config=${2:?give the race scenario TOML}
    shift 2
    local ego
    for ego in $(egos_or_all "$@"); do
        nice "$bin" eval "$ego" --config "$config" --track f1_esp --rivals "$rivals" \
            --workers 1 --contexts "$contexts" --laps "${CTXRACE_LAPS:-50}" --seed "${SEED:-0}" \
            --fresh --out "$dir/ctxrace-$variant/$ego"
        # the records: meta.json, contexts.csv, episodes.csv (the rest is the worker's or a figure)
        rm -f "$dir/ctxrace-$variant/$ego"/{job.json,contexts.json,episode.png,episode.svg} \
            "$dir/ctxrace-$variant/$ego"/episodes.part-*.csv
    done
}

case ${1:-} in
    setup) setup ;;
    paper) shift; paper "$@" ;;
    ctxrace) shift; ctxrace_side "$@" ;;
    table) python3 deploy/paper_sim_agreement_table.py table "$raw" "${2:?give the variant}" docs/table2/sim_agreement.csv ;;
    compare) shift; python3 deploy/paper_sim_agreement_table.py compare "$dir" "$@" ;;
    all)
        setup
        paper
        ctxrace_side paper-code configs/scenarios/paper-code.toml
        ctxrace_side table-era configs/scenarios/paper-code-table-era.toml
        python3 deploy/paper_sim_agreement_table.py table "$raw" paper-code docs/table2/sim_agreement.csv
        python3 deploy/paper_sim_agreement_table.py compare "$dir" paper-code table-era
        ;;
    *) sed -n '2,40p' "$0" | sed -n '/^#   deploy/,/^# EGO/p' >&2; exit 2 ;;
esac
