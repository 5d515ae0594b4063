"""Short stable names for JSON-able trees: config hashes, cache keys, evaluation-set fingerprints."""

from __future__ import annotations

import hashlib
import json
from typing import Any

__all__ = ["json_digest"]


def json_digest(tree: Any, length: int = 16, sort_keys: bool = True) -> str:
    """The first ``length`` hex digits of the SHA-256 of ``tree`` as JSON.

    Sorted keys make the name independent of dict order, so equal trees always share it;
    ``sort_keys=False`` only keeps names that were recorded before this helper existed.
    """
    return hashlib.sha256(json.dumps(tree, sort_keys=sort_keys).encode()).hexdigest()[:length]
