"""Files a user or a data set names, opened and read within stated bounds.

A data set from a mirror, a colleague's checkpoint or another tool's depth maps may be hostile: a
symbolic link to ``/dev/zero`` reads forever, a FIFO blocks the ``open`` itself, a 3 MB gzip of zeros
decompresses to gigabytes, an ``.npy`` header may promise ``(100000, 100000)`` with no data behind it,
and JSON nested 100,000 deep overflows Python's parser. So every reader opens through
:func:`open_regular` (non-blocking open, then ``fstat`` of the descriptor itself: no race between
the check and the read) and reads through a bounded function here, each refusal a ``ValueError`` that
names the file and the cap. The caps (also in docs/security.md):

- :data:`MAX_TEXT_BYTES`: a JSON or text file read whole (set lists, split files, metadata, manifests);
- :func:`annotation_cap`: a decompressed annotation file (``CDM_MAX_ANNOTATION_MIB``, default 256 MiB:
  ~320,000 Co3D frame entries of ~830 bytes);
- :data:`MAX_JSON_DEPTH`: nesting of any JSON read (Co3D's annotations nest 4 deep);
- :data:`MAX_INT_DIGITS`: digits of an integer in any JSON read (a 5,001-digit one is named, field and file);
- :data:`MAX_ARRAY_BYTES`: one ``.npy`` array or ``.npz`` member, from its header before allocation,
  and :data:`MAX_NPZ_BYTES` all members of an ``.npz`` together.
"""

from __future__ import annotations

import gzip
import json
import os
import re
import stat
import zipfile
import zlib
from pathlib import Path
from typing import IO, Any

import numpy as np
import yaml

__all__ = [
    "MAX_ARRAY_BYTES",
    "MAX_INT_DIGITS",
    "MAX_JSON_DEPTH",
    "MAX_NPZ_BYTES",
    "MAX_TEXT_BYTES",
    "PLAIN_NAME",
    "BoundedYamlLoader",
    "annotation_cap",
    "bracket_depth",
    "inside",
    "load_npy",
    "load_npz",
    "object_id_parts",
    "open_regular",
    "parse_json",
    "plain_name",
    "read_bounded",
    "read_gzip",
    "read_json",
]

MAX_TEXT_BYTES = 64 * 2**20
"""Most bytes of a JSON or text file read whole (Co3D's largest set list is a few MB)."""
MAX_JSON_DEPTH = 64
"""Most nesting of ``[`` and ``{`` in any JSON read."""
MAX_INT_DIGITS = 1000
"""Most digits of an integer in any JSON read (Python's own ``int()`` stops at 4300, naming nothing)."""
MAX_ARRAY_BYTES = 512 * 2**20
"""Most bytes of one array read from ``.npy`` or one ``.npz`` member (an 8,192² float64 depth map)."""
MAX_NPZ_BYTES = 512 * 2**20
"""Most bytes of all arrays of one ``.npz`` together, from their headers."""
ANNOTATION_ENV = "CDM_MAX_ANNOTATION_MIB"
"""Environment variable raising (or lowering) the decompressed-annotation cap, in MiB."""
_DEFAULT_ANNOTATION_MIB = 256

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def open_regular(path: Path, label: str, show_path: bool = True) -> IO[bytes]:
    """``path`` opened for binary reading if it is a regular file (after links); ValueError otherwise.

    The open does not block (``O_NONBLOCK``: a FIFO with no writer would hang it), and the kind is
    read from the open descriptor, so no file can be swapped in between the check and the read.
    ``label`` starts the message (the field or option that named the file; with ``show_path=False``
    it names the path itself).
    """
    where = f"{label}: {path}" if show_path else label
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise ValueError(f"{where} does not exist") from None
    except OSError as exc:
        raise ValueError(f"{where} cannot be opened: {exc.strerror}") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
        raise ValueError(f"{where} is {kind}; expected a regular file")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def read_bounded(path: Path, label: str, cap: int = MAX_TEXT_BYTES, show_path: bool = True) -> bytes:
    """The bytes of the regular file ``path``, refused past ``cap`` bytes before reading them (messages
    as :func:`open_regular`'s)."""
    with open_regular(path, label, show_path) as f:
        size = os.fstat(f.fileno()).st_size
        if size > cap:
            raise ValueError(f"{label}: {path} is {size} bytes; at most {cap} are read" if show_path
                             else f"{label} is {size} bytes; at most {cap} are read")
        return f.read(size + 1)[:cap]  # not read(cap): a reader allocates the size it is asked for


def annotation_cap() -> int:
    """The decompressed-annotation cap in bytes: ``$CDM_MAX_ANNOTATION_MIB`` MiB, or 256 MiB."""
    text = os.environ.get(ANNOTATION_ENV, str(_DEFAULT_ANNOTATION_MIB))
    if not (text.isascii() and text.isdigit() and 0 < len(text) <= 7 and int(text) > 0):
        raise ValueError(f"{ANNOTATION_ENV}: {text[:40]!r}; give a whole number of MiB, 1 to 9999999")
    return int(text) * 2**20


def read_gzip(path: Path, label: str, cap: int | None = None) -> bytearray:
    """``path`` gunzipped, refused (naming the file and the cap) as soon as it passes ``cap`` bytes
    (default :func:`annotation_cap`): memory stays near the cap whatever the compression ratio."""
    cap = annotation_cap() if cap is None else cap
    out = bytearray()
    try:
        with open_regular(path, label) as f, gzip.GzipFile(fileobj=f) as gz:
            while chunk := gz.read(2**20):
                out += chunk
                if len(out) > cap:
                    raise ValueError(f"{label}: {path} decompresses to more than {cap // 2**20} MiB; set "
                                     f"{ANNOTATION_ENV} higher if the file is genuine")
    except (OSError, EOFError, zlib.error) as exc:  # gzip.BadGzipFile is an OSError
        raise ValueError(f"{label}: cannot read {path}: {exc}") from None
    return out  # not bytes(out): a copy would double the peak for a file near the cap


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


class BoundedYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader whose integers and dates fail as a ``yaml.YAMLError`` at their line and
    column: an integer of more than :data:`MAX_INT_DIGITS` digits (Python's ``int()`` stops at 4300
    naming nothing) or a date that does not exist (``2026-02-30``: a bare ``ValueError`` otherwise).
    Every reader of a YAML file or value (configs, ``--set``, sweep specs) loads with it."""


def _bounded_yaml_int(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> int:
    digits = sum(c.isdigit() for c in str(node.value))
    if digits > MAX_INT_DIGITS:
        raise yaml.constructor.ConstructorError(
            None, None, f"an integer of {digits} digits; numbers read here have at most {MAX_INT_DIGITS}",
            node.start_mark)
    return loader.construct_yaml_int(node)


def _checked_yaml_timestamp(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> Any:
    try:
        return loader.construct_yaml_timestamp(node)
    except ValueError as exc:
        raise yaml.constructor.ConstructorError(None, None, f"{node.value!r} is no date ({exc})",
                                                node.start_mark) from None


BoundedYamlLoader.add_constructor("tag:yaml.org,2002:int", _bounded_yaml_int)
BoundedYamlLoader.add_constructor("tag:yaml.org,2002:timestamp", _checked_yaml_timestamp)


def read_json(path: Path, label: str, gzipped: bool = False) -> Any:
    """The JSON file ``path`` (gunzipped first with ``gzipped``), every cap of this module applied."""
    raw = read_gzip(path, label) if gzipped else read_bounded(path, label)
    return parse_json(raw, label, path)


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


def _array_header(f: IO[bytes], label: str, path: Path, cap: int) -> tuple[tuple[int, ...], np.dtype, int]:
    """Shape, dtype and byte count from the ``.npy`` header at ``f``'s position, refused past ``cap``
    bytes (or for object arrays) before anything is allocated."""
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"format version {version}")
    except (ValueError, EOFError, OSError) as exc:
        raise ValueError(f"{label}: {path} is not a .npy array ({exc})") from None
    if dtype.hasobject:
        raise ValueError(f"{label}: {path} holds Python objects, refused (reading them would unpickle the file)")
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if nbytes > cap:
        raise ValueError(
            f"{label}: {path} declares a {dtype} array of shape {tuple(shape)} ({nbytes / 2**30:.1f} GiB); "
            f"an array read here may hold at most {cap // 2**20} MiB"
        )
    return tuple(shape), dtype, nbytes


def load_npy(path: Path, label: str, cap: int = MAX_ARRAY_BYTES) -> np.ndarray:
    """The ``.npy`` array at ``path``: a regular file whose header declares at most ``cap`` bytes, all
    of them present (checked against the file's size before allocating)."""
    with open_regular(path, label) as f:
        _, _, nbytes = _array_header(f, label, path, cap)
        if os.fstat(f.fileno()).st_size < f.tell() + nbytes:
            raise ValueError(f"{label}: {path} is shorter than its header says ({nbytes} bytes of data); truncated")
        f.seek(0)
        try:
            return np.load(f, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"{label}: {path} is not a .npy array ({exc})") from None


def load_npz(path: Path, label: str, names: bool = False, cap: int = MAX_ARRAY_BYTES,
             total: int = MAX_NPZ_BYTES) -> dict[str, np.ndarray] | list[str]:
    """Every array of the ``.npz`` at ``path`` by name (``names``: only the names, nothing decompressed).

    Each member's header is read first and refused past ``cap`` bytes, all of them together past
    ``total``; a member is then read no further than its header says.
    """
    with open_regular(path, label) as f:
        try:
            archive = zipfile.ZipFile(f)
        except (zipfile.BadZipFile, OSError, ValueError) as exc:
            raise ValueError(f"{label}: {path} is not an .npz file ({exc})") from None
        with archive:
            members = [i for i in archive.infolist() if i.filename.endswith(".npy")]
            keys = [i.filename.removesuffix(".npy") for i in members]
            if names:
                return keys
            try:
                return _npz_arrays(archive, members, keys, label, path, cap, total)
            except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
                raise ValueError(f"{label}: {path} is a damaged .npz file ({exc})") from None


def _npz_arrays(archive: zipfile.ZipFile, members: list[zipfile.ZipInfo], keys: list[str], label: str, path: Path,
                cap: int, total: int) -> dict[str, np.ndarray]:
    declared = 0
    for info in members:
        with archive.open(info) as member:
            declared += _array_header(member, label, Path(f"{path}:{info.filename}"), cap)[2]
        if declared > total:
            raise ValueError(f"{label}: {path} declares more than {total // 2**20} MiB of arrays; at most that is read")
    out = {}
    for key, info in zip(keys, members):
        with archive.open(info) as member:
            try:
                out[key] = np.lib.format.read_array(member, allow_pickle=False)
            except ValueError as exc:
                raise ValueError(f"{label}: {path}:{info.filename} is not a .npy array ({exc})") from None
    return out
