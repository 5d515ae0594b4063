"""Names and relative paths a data set's files give, checked before they become part of a path.

A sequence name ``../../x`` or an annotation path ``/etc/passwd`` would read (or, in a cache, write)
outside the data root; each is refused with a ``ValueError`` naming the file and entry.
"""

from __future__ import annotations

import re

__all__ = ["PLAIN_NAME", "inside", "object_id_parts", "plain_name"]

PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")
"""One plain file name: letters, digits, ``_ . -``, not starting with a dot, at most 128 characters."""


def plain_name(name: object, where: str) -> str:
    """``name`` if it is one plain file name (letters, digits, ``_ . -``, not starting with a dot, at
    most 128 characters), as every sequence, model and category of the published data sets is;
    ValueError naming ``where`` (the file and entry) otherwise. A name that becomes part of a path we
    read or write can then neither climb out (``..``) nor descend (``/``)."""
    if not isinstance(name, str) or not PLAIN_NAME.fullmatch(name):
        raise ValueError(f"{where} names {str(name)[:80]!r}; expected a plain name (letters, digits, "
                         "'_', '.', '-'; not starting with '.')")
    return name


def object_id_parts(object_id: object, where: str) -> list[str]:
    """The parts of an object id ``<kind>/<category>/<name>``, each a :func:`plain_name`."""
    parts = str(object_id).split("/")
    if not isinstance(object_id, str) or len(parts) != 3:
        raise ValueError(f"{where} names object {str(object_id)[:80]!r}; expected <kind>/<category>/<name>")
    return [plain_name(p, where) for p in parts]


def inside(relative: str, where: str) -> str:
    """``relative``, a path an annotation gives below a data root, if it stays below it: not absolute,
    no ``..`` part, no NUL; ValueError starting with ``where`` (the field, file and entry) otherwise.

    Checked on the text, not on the resolved path: a root whose folders are links to other disks is
    a layout users make, and those links are theirs, not the annotation's."""
    if not isinstance(relative, str) or not relative or "\0" in relative:
        raise ValueError(f"{where} gives the path {str(relative)[:80]!r}; expected a relative path")
    parts = relative.replace("\\", "/").split("/")
    if relative.startswith(("/", "\\")) or ".." in parts or (len(parts[0]) > 1 and parts[0][1] == ":"):
        raise ValueError(f"{where} gives the path {relative[:200]!r}, which leaves the data root; "
                         "paths in annotations must stay below it")
    return relative
