"""Run a `python -m dbdjax.training.<name>` command line in a fresh interpreter, as a user would."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def help_text(module: str) -> str:
    """The --help output of `python -m <module>` (the repository on PYTHONPATH, JAX on the CPU);
    fails the calling test with the command's stderr if it does not exit with 0."""
    completed = subprocess.run(
        [sys.executable, "-m", module, "--help"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu"},
        timeout=120,
    )
    assert completed.returncode == 0, completed.stderr
    return completed.stdout
