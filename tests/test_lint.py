"""Pyflakes checks (ruff, rules in ``pyproject.toml``) over the project's code: an undefined name or a
shadowed import fails only on the path that reaches it, which a test may never take."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_code_passes_pyflakes_checks():
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--output-format", "concise", "--no-cache",
                          "benchmark", "methods", "annotations", "tests"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
