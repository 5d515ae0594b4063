"""Every outside byte through one package: no module of ``cdm/`` or ``sweeps/`` outside ``cdm/io/`` opens a
file to read it or parses one (issue 55, docs/security.md), and no ``torch.load``, ``torch.jit.load``,
``pickle.load(s)`` or ``np.load(allow_pickle=True)`` anywhere in the code (issues 49, 59): the project's own
files are safetensors and JSON, foreign torch files go through cdm/io/torch's inert unpickler."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOOR = Path("cdm/io")
"""The package every read of a file a user, a data set or a neighbour can write goes through."""
SCANNED = ("cdm", "sweeps", "benchmarks", "tests")
AUDITED = ("cdm", "sweeps")
EXEMPT = {Path("tests/test_hostile_torch.py"): ["torch.jit.load", "torch.load"],
          Path("tests/test_io_torch_legacy.py"): ["torch.load"],
          Path("tests/test_store_runs.py"): ["pickle.loads"]}
"""Tests that call a reader on purpose: positive controls (a hostile file shown live, torch's own reader
shown unpoisoned after a refusal, torch's reading of the test's own legacy files as the reference) and a
round trip of the test's own object (Tune pickles its callbacks)."""
ALLOWED = {Path("cdm/provenance.py"): {".read_text": "/proc/cpuinfo: the kernel's description of the CPU, "
                                                        "written by no one"},
           Path("sweeps/execute/local_cluster.py"): {".read_bytes": "/proc/<pid>/cmdline: the kernel's view of a "
                                                                    "process (its size reads 0), written by no one",
                                                       ".read_text": "/proc/<pid>/stat: the kernel's process table, "
                                                                     "written by no one"},
           Path("cdm/lab.py"): {".read_text": "--version: pip's own install record of this package "
                                              "(importlib.metadata's direct_url.json)",
                                "json.loads": "--version: the commit in pip's own install record"}}
"""Reads outside ``cdm/io/`` kept on purpose, each with its reason."""

PICKLE_READERS = {"torch.load", "torch.jit.load", "pickle.load", "pickle.loads", "_pickle.load", "_pickle.loads",
                  "dill.load", "joblib.load", "torch.serialization.load"}
FILE_READERS = PICKLE_READERS | {
    "open", "io.open", "gzip.open", "gzip.GzipFile", "zipfile.ZipFile", "tarfile.open", "numpy.load",
    "json.load", "json.loads", "yaml.load", "yaml.safe_load", "yaml.full_load", "yaml.unsafe_load", "yaml.load_all",
    "yaml.safe_load_all", "yaml.parse", "yaml.compose", "cv2.imread", "PIL.Image.open", "trimesh.load",
    "trimesh.load_mesh", "numpy.loadtxt", "numpy.genfromtxt", "numpy.fromfile", "pyarrow.parquet.read_table",
    "pyarrow.parquet.ParquetFile", "pyarrow.parquet.ParquetDataset", "pyarrow.parquet.read_pandas",
    "pyarrow.csv.read_csv", "pyarrow.csv.open_csv", "pyarrow.json.read_json", "pyarrow.feather.read_table",
    "pyarrow.feather.read_feather"}
"""Calls that read or parse a file's bytes, by the name they resolve to (``open`` only in a read mode)."""
READ_METHODS = ("read_text", "read_bytes", "open_input_stream", "open_input_file")
"""Methods that read a file: ``pathlib.Path``'s that read it whole, and a pyarrow file system's input streams
(a sweep folder in an object store: :func:`cdm.io.files.read_from`); ``x.open()`` counts too, in a read mode."""


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _allows_pickle(call: ast.Call) -> bool:
    return any(k.arg == "allow_pickle" and not (isinstance(k.value, ast.Constant) and k.value.value is False)
               for k in call.keywords)


def _reads(call: ast.Call, position: int) -> bool:
    """Whether an ``open`` call's mode (keyword, or the argument at ``position``) reads: absent, or only r/b/t."""
    mode = next((k.value for k in call.keywords if k.arg == "mode"),
                call.args[position] if len(call.args) > position else ast.Constant("r"))
    return not isinstance(mode, ast.Constant) or set(str(mode.value)) <= set("rbt")


def _is_class(node: ast.AST) -> bool:
    """Whether ``node`` names a class (``PreparedRoot``): its ``open`` is a constructor of the project's, not a read."""
    return isinstance(node, ast.Name) and node.id[:1].isupper()


def _calls(source: str) -> list[tuple[ast.Call, str]]:
    """Every call in ``source`` with the dotted name it resolves to: aliases (``from torch import load``,
    ``import pickle as p``, ``np``) are followed to what they name."""
    tree = ast.parse(source)
    alias: dict[str, str] = {"np": "numpy"}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            alias.update({a.asname or a.name: a.name for a in node.names})
        elif isinstance(node, ast.ImportFrom) and node.module:
            alias.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names})
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            head, _, rest = _dotted(node.func).partition(".")
            out.append((node, f"{alias.get(head, head)}.{rest}" if rest else alias.get(head, head)))
    return out


def readers(source: str) -> list[str]:
    """The pickle-reading calls in ``source``, as ``line: name``."""
    found = []
    for node, full in _calls(source):
        if full in PICKLE_READERS:
            found.append(f"{node.lineno}: {full}")
        elif full == "numpy.load" and _allows_pickle(node):
            found.append(f"{node.lineno}: {full}(allow_pickle=True)")
    return found


def file_reads(source: str) -> list[str]:
    """The calls in ``source`` that open a file to read it or parse one, as ``line: name``; a method call
    is named by its attribute alone (``.read_text``, ``.open``)."""
    found = []
    for node, full in _calls(source):
        method = node.func.attr if isinstance(node.func, ast.Attribute) else None
        if full in FILE_READERS and (full not in ("open", "io.open") or _reads(node, 1)):
            found.append(f"{node.lineno}: {full}")
        elif method in READ_METHODS or (method == "open" and full not in FILE_READERS | {"os.open"}
                                        and not _is_class(node.func.value) and _reads(node, 0)):
            found.append(f"{node.lineno}: .{method}")
    return found


def _files(folders: tuple[str, ...]) -> list[Path]:
    return sorted(p for folder in folders for p in (ROOT / folder).rglob("*.py") if ".venv" not in p.parts)


def _names(found: list[str]) -> list[str]:
    return sorted({line.split(": ", 1)[1] for line in found})


def test_no_module_calls_a_pickle_reader():
    # The project's own files are safetensors and JSON (cdm/io/safetensors.py); foreign torch files go through
    # cdm/io/torch's inert unpickler, which calls no reader either.
    offenders = {str(p.relative_to(ROOT)): found for p in _files(SCANNED)
                 if (found := readers(p.read_text())) and _names(found) != EXEMPT.get(p.relative_to(ROOT))}
    assert offenders == {}


def test_every_read_of_a_file_outside_cdm_io_is_one_the_allow_list_names():
    offenders = {}
    for path in _files(AUDITED):
        relative = path.relative_to(ROOT)
        if relative.is_relative_to(DOOR):
            continue
        found = [line for line in file_reads(path.read_text())
                 if line.split(": ", 1)[1] not in ALLOWED.get(relative, {})]
        if found:
            offenders[str(relative)] = found
    assert offenders == {}, "read these through cdm/io (docs/security.md), or allow-list them with a reason"


def test_every_allowed_read_is_still_there_and_has_its_reason():
    for path, reads in ALLOWED.items():
        found = _names(file_reads((ROOT / path).read_text()))
        assert sorted(reads) == found and all(len(why) > 20 for why in reads.values())


@pytest.mark.parametrize("snippet,pickles,reads", [
    ("import torch\ntorch.load('x')\n", ["2: torch.load"], ["2: torch.load"]),
    ("import torch\nm = torch.jit.load('x')\n", ["2: torch.jit.load"], ["2: torch.jit.load"]),
    ("from torch import load as L\nL('x')\n", ["2: torch.load"], ["2: torch.load"]),
    ("import pickle as p\np.loads(b'')\n", ["2: pickle.loads"], ["2: pickle.loads"]),
    ("import numpy as np\nnp.load('x', allow_pickle=True)\n", ["2: numpy.load(allow_pickle=True)"], ["2: numpy.load"]),
    ("import numpy as np\nnp.load('x', allow_pickle=False)\n", [], ["2: numpy.load"]),
    ("import torch\ntorch.save({}, 'x')\n", [], []),
    ("open('x')\n", [], ["1: open"]),
    ("open('x', 'rb')\n", [], ["1: open"]),
    ("open('x', mode='r', newline='')\n", [], ["1: open"]),
    ("open('x', 'w')\n", [], []),
    ("open('x', 'a+')\n", [], []),
    ("from pathlib import Path\nPath('x').read_text()\n", [], ["2: .read_text"]),
    ("p.read_bytes()\n", [], ["1: .read_bytes"]),
    ("with p.open(newline='') as f:\n    pass\n", [], ["1: .open"]),
    ("p.open('wb')\n", [], []),
    ("PreparedRoot.open(root, kind)\n", [], []),
    ("import os\nos.open('x', os.O_RDONLY)\n", [], []),
    ("import yaml\nyaml.safe_load(s)\n", [], ["2: yaml.safe_load"]),
    ("import json\njson.loads(s)\n", [], ["2: json.loads"]),
    ("from json import load\nload(f)\n", [], ["2: json.load"]),
    ("import cv2\ncv2.imread('x')\n", [], ["2: cv2.imread"]),
    ("from PIL import Image\nImage.open('x')\n", [], ["2: PIL.Image.open"]),
    ("import gzip\ngzip.open('x')\n", [], ["2: gzip.open"]),
    ("import zipfile\nzipfile.ZipFile('x')\n", [], ["2: zipfile.ZipFile"]),
    ("import trimesh\ntrimesh.load_mesh('x')\n", [], ["2: trimesh.load_mesh"]),
    ("import json\njson.dumps(x)\n", [], []),
    ("from pyarrow import fs\nf, p = fs.FileSystem.from_uri(u)\nf.open_input_stream(p)\n", [],
     ["3: .open_input_stream"]),
    ("with filesystem.open_input_file(p) as s:\n    pass\n", [], ["1: .open_input_file"]),
    ("filesystem.open_output_stream(p)\n", [], []),
    ("import pyarrow.parquet as pq\npq.read_table('x')\n", [], ["2: pyarrow.parquet.read_table"]),
    ("from pyarrow import csv\ncsv.read_csv('x')\n", [], ["2: pyarrow.csv.read_csv"]),
    ("import numpy as np\nnp.loadtxt(lines)\n", [], ["2: numpy.loadtxt"]),
    ("from numpy import genfromtxt\ngenfromtxt('x')\n", [], ["2: numpy.genfromtxt"]),
])
def test_the_audits_find_a_planted_call(snippet, pickles, reads):
    assert (readers(snippet), file_reads(snippet)) == (pickles, reads)
