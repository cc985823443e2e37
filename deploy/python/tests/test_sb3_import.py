"""Stable-Baselines3 stays optional: ``import ctxrace`` loads neither it nor torch, and without
it ``import ctxrace.sb3`` says how to install it (these run where SB3 is not installed, as in
CI; test_sb3.py checks the adapter itself)."""

import subprocess
import sys


def python(code: str) -> subprocess.CompletedProcess:
    """`code` run by this Python in a fresh process."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)


def test_import_ctxrace_loads_neither_sb3_nor_torch():
    run = python(
        "import sys, ctxrace; "
        "print(sorted({'stable_baselines3', 'torch'} & set(sys.modules)))"
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


def test_without_sb3_ctxrace_sb3_names_the_install():
    # None in sys.modules makes `import stable_baselines3` fail as if it were not installed
    run = python("import sys; sys.modules['stable_baselines3'] = None; import ctxrace.sb3")
    assert run.returncode != 0
    assert "ImportError: ctxrace.sb3 needs Stable-Baselines3: pip install stable-baselines3" in (
        run.stderr
    )
    assert "pip install torch --index-url https://download.pytorch.org/whl/cpu" in run.stderr
