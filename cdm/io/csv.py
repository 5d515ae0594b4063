"""Tables a run or a neighbour wrote as CSV (per-object scores), read whole within the text cap."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from cdm.io.files import read_text

__all__ = ["read_csv"]


def read_csv(path: Path, label: str) -> list[dict[str, str]]:
    """The rows of the CSV file ``path`` by its header's names (:func:`cdm.io.files.read_text`'s caps and
    refusals, ``label`` naming the file)."""
    try:
        return list(csv.DictReader(io.StringIO(read_text(path, label), newline="")))
    except csv.Error as exc:
        raise ValueError(f"{label}: {path} is not CSV ({exc})") from None
