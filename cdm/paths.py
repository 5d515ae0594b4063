"""Paths of local inputs as configured: ``$VARIABLES`` and ``~`` expanded; a URI told apart from a path.

Sweep specs name their external inputs under ``$CDM_INPUTS`` (docs/paper.md, "External inputs"), so one
spec serves every machine; the expansion happens where a file is opened, in the process that opens it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["input_path", "names_a_uri"]

_URI = re.compile(r"[A-Za-z][A-Za-z0-9+.-]+:/")
"""A scheme of two or more characters then ``:/`` (``runs:/``, ``s3://``, ``file:///``): never a local path,
which has no scheme, nor a Windows drive (``C:\\``, one letter)."""


def input_path(text: str | Path) -> Path:
    """``text`` with environment variables and ``~`` expanded (an unset variable stays as written)."""
    return Path(os.path.expandvars(str(text))).expanduser()


def names_a_uri(text: str) -> bool:
    """Whether ``text`` is a URI (``runs:/…``, ``s3://…``) rather than a local path: the library reads local
    files only, and says so instead of reporting a missing file."""
    return _URI.match(text) is not None
