"""The tree is clean under ruff, configured in pyproject.toml (line length 120; rules E, F, W, I, B), so the
README's test command is also the lint step of CI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing_in_the_tree():
    done = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", "."],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, f"ruff check . (pyproject.toml [tool.ruff]) reports:\n{done.stdout}{done.stderr}"
