"""One module reads pickles: no ``torch.load``, ``torch.jit.load``, ``pickle.load(s)`` or
``np.load(allow_pickle=True)`` anywhere else in the code (issue 49, docs/security.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OWNER = Path("cdm/torch_files.py")
"""The one module that may call torch's loader (its ``load_own``: the cache's own memory-mapped files)."""
SCANNED = ("cdm", "sweeps", "benchmarks", "tests")
EXEMPT = {Path("tests/test_hostile_torch.py"): ["torch.jit.load", "torch.load"],
          Path("tests/test_torch_legacy.py"): ["torch.load"],
          Path("tests/test_tracking.py"): ["pickle.loads"]}
"""Tests that call a reader on purpose: positive controls (a hostile file shown live, torch's own reader
shown unpoisoned after a refusal, torch's reading of the test's own legacy files as the reference) and a
round trip of the test's own object (Tune pickles its callbacks)."""


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _allows_pickle(call: ast.Call) -> bool:
    return any(k.arg == "allow_pickle" and not (isinstance(k.value, ast.Constant) and k.value.value is False)
               for k in call.keywords)


def readers(source: str) -> list[str]:
    """The pickle-reading calls in ``source``, as ``line: name``; aliases (``from torch import load``,
    ``import pickle as p``) are resolved to what they name."""
    tree = ast.parse(source)
    alias: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            alias.update({a.asname or a.name: a.name for a in node.names})
        elif isinstance(node, ast.ImportFrom) and node.module:
            alias.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names})
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func)
        head, _, rest = name.partition(".")
        full = f"{alias.get(head, head)}.{rest}" if rest else alias.get(head, head)
        if full in {"torch.load", "torch.jit.load", "pickle.load", "pickle.loads", "_pickle.load",
                    "_pickle.loads", "dill.load", "joblib.load", "torch.serialization.load"}:
            found.append(f"{node.lineno}: {full}")
        elif full in {"numpy.load", "np.load"} and _allows_pickle(node):
            found.append(f"{node.lineno}: {full}(allow_pickle=True)")
    return found


def _files() -> list[Path]:
    return sorted(p for folder in SCANNED for p in (ROOT / folder).rglob("*.py") if ".venv" not in p.parts)


def _names(found: list[str]) -> list[str]:
    return sorted({line.split(": ", 1)[1] for line in found})


def test_only_the_owning_module_reads_pickles():
    offenders = {str(p.relative_to(ROOT)): found for p in _files()
                 if p.relative_to(ROOT) != OWNER and (found := readers(p.read_text()))
                 and _names(found) != EXEMPT.get(p.relative_to(ROOT))}
    assert offenders == {}


def test_the_owner_reads_with_torchs_weights_only_reader_alone():
    text = (ROOT / OWNER).read_text()
    assert _names(readers(text)) == ["torch.load"] and "weights_only=False" not in text


@pytest.mark.parametrize("snippet,expected", [
    ("import torch\ntorch.load('x')\n", ["2: torch.load"]),
    ("import torch\nm = torch.jit.load('x')\n", ["2: torch.jit.load"]),
    ("from torch import load as L\nL('x')\n", ["2: torch.load"]),
    ("import pickle as p\np.loads(b'')\n", ["2: pickle.loads"]),
    ("import numpy as np\nnp.load('x', allow_pickle=True)\n", ["2: numpy.load(allow_pickle=True)"]),
    ("import numpy as np\nnp.load('x', allow_pickle=False)\n", []),
    ("import torch\ntorch.save({}, 'x')\n", []),
])
def test_the_audit_finds_a_planted_call(snippet, expected):
    assert readers(snippet) == expected
