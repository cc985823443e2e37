#!/usr/bin/env bash
# The Python package's checks, for .ci/run after the cargo tests: the wheel built once into a
# fresh venv outside the repository, then the pytest suite (against target/release/ctxrace).
set -euo pipefail
cd "$(dirname "$0")"
venv="${CTXRACE_PY_VENV:-${TMPDIR:-/tmp}/ctxrace-py-ci}"
python3 -m venv --clear "$venv"
"$venv/bin/pip" install --quiet --upgrade pip
"$venv/bin/pip" install --quiet ".[test]"
"$venv/bin/python" -m pytest -q tests
