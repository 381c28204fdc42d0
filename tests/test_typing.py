"""The whole tree type-checks: mypy with the pyproject's settings (`[tool.mypy] files`) reports no error."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_mypy_reports_no_error_over_the_whole_tree():
    # Run from the project root so mypy reads pyproject.toml and keeps its cache in .mypy_cache (a warm
    # cache checks in under a second; a clean clone's first run takes about ten seconds).
    proc = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, f"mypy failed (exit {proc.returncode}):\n{proc.stdout}{proc.stderr}"
