"""JSON a user, a data set or a neighbour wrote, parsed within stated bounds.

JSON nested 100,000 deep overflows Python's parser, and an integer of 5,001 digits stops ``int()``
with a message naming neither file nor field. So every JSON text is measured before the parser sees
it. The caps (also in docs/security.md):

- :data:`MAX_JSON_DEPTH`: nesting of any JSON read (Co3D's annotations nest 4 deep);
- :data:`MAX_INT_DIGITS`: digits of an integer in any JSON read (a 5,001-digit one is named, field and file);
- the file's size: :data:`cdm.io.files.MAX_TEXT_BYTES`, or the annotation cap when gzipped.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from cdm.io.files import read_bounded, read_gzip

__all__ = ["MAX_INT_DIGITS", "MAX_JSON_DEPTH", "bracket_depth", "parse_json", "read_json"]

MAX_JSON_DEPTH = 64
"""Most nesting of ``[`` and ``{`` in any JSON read."""
MAX_INT_DIGITS = 1000
"""Most digits of an integer in any JSON read (Python's own ``int()`` stops at 4300, naming nothing)."""

_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')
_BRACKETS = bytes(range(256)).translate(None, b"[]{}")
"""Every byte but the four brackets: deleted from a JSON text, what remains is its nesting."""


def bracket_depth(raw: bytes | bytearray) -> int:
    """Deepest bracket nesting of the JSON (or YAML flow) text ``raw`` outside double-quoted strings; an
    upper bound where brackets sit in other quoting."""
    # Strings may hold brackets; dropping them first keeps the count honest for valid JSON.
    brackets = np.frombuffer(_STRING.sub(b"", raw).translate(None, _BRACKETS), np.uint8)
    depth = deepest = 0
    for start in range(0, len(brackets), 2**20):  # in steps: a 256 MiB annotation holds tens of millions
        chunk = brackets[start : start + 2**20]
        running = depth + np.cumsum(np.where((chunk == ord("[")) | (chunk == ord("{")), 1, -1), dtype=np.int64)
        deepest, depth = max(deepest, int(running.max())), int(running[-1])
    return deepest


def parse_json(raw: bytes | bytearray, label: str, path: Path) -> Any:
    """``raw`` (the contents of ``path``) as JSON, refused past :data:`MAX_JSON_DEPTH` levels of nesting
    before the parser sees it."""
    if (depth := bracket_depth(raw)) > MAX_JSON_DEPTH:
        raise ValueError(f"{label}: {path} nests {depth} levels deep; JSON read here may nest at most {MAX_JSON_DEPTH}")
    try:
        return json.loads(raw, parse_int=_bounded_int)
    except _LongNumber:
        key = _LONG_NUMBER_KEY.search(raw)
        field = f"field {key[1].decode(errors='replace')!r}" if key else "a number"
        raise ValueError(f"{label}: {path}: {field} has more than {MAX_INT_DIGITS} digits; "
                         f"numbers read here have at most {MAX_INT_DIGITS}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{label}: {path} is not JSON ({exc})") from None


class _LongNumber(Exception):
    """An integer past :data:`MAX_INT_DIGITS` digits in a JSON text."""


_LONG_NUMBER_KEY = re.compile(rb'"([^"\\]{1,80})"\s*:\s*-?[0-9]{%d}' % (MAX_INT_DIGITS + 1))


def _bounded_int(text: str) -> int:
    # Python refuses int() past 4300 digits with a message naming neither file nor field.
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise _LongNumber
    return int(text)


def read_json(path: Path, label: str, gzipped: bool = False) -> Any:
    """The JSON file ``path`` (gunzipped first with ``gzipped``), every cap of this module applied."""
    raw = read_gzip(path, label) if gzipped else read_bounded(path, label)
    return parse_json(raw, label, path)


