"""Paths of local inputs as configured: ``$VARIABLES`` and ``~`` expanded.

Sweep specs name their external inputs under ``$CDM_INPUTS`` (docs/paper.md, "External inputs"), so one
spec serves every machine; the expansion happens where a file is opened, in the process that opens it.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["input_path"]


def input_path(text: str | Path) -> Path:
    """``text`` with environment variables and ``~`` expanded (an unset variable stays as written)."""
    return Path(os.path.expandvars(str(text))).expanduser()
