"""The metric record (:mod:`cdm.metric_names`) is the one home of every metric: no other module of ``cdm/`` or
``sweeps/`` spells a metric's name (``"cd"``, ``"eval/f1"``, ``f"baseline/{b}/cd"``) in its code, and a metric
declared there alone reaches MLflow, the results table, the verdicts and the report."""

from __future__ import annotations

import ast
from pathlib import Path

from cdm.metric_names import METRICS

ROOT = Path(__file__).resolve().parents[1]
HOME = ROOT / "cdm" / "metric_names.py"


def _strings(tree: ast.AST) -> list[ast.Constant]:
    """Every string constant of the code, f-string parts included, docstrings (of modules, classes, functions
    and attributes: strings standing as statements) left out: they explain."""
    docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
    return [n for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


def _names_a_metric(text: str) -> bool:
    """``cd``, or a key with ``cd`` between slashes (``eval/cd``, ``/cd``, ``final/f1/chair``)."""
    return text in METRICS or ("/" in text and any(part in METRICS for part in text.split("/")))


def test_no_module_but_the_record_spells_a_metric_name():
    found = [f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}"
             for path in sorted([*ROOT.glob("cdm/**/*.py"), *ROOT.glob("sweeps/**/*.py")]) if path != HOME
             for node in _strings(ast.parse(path.read_text(encoding="utf-8"))) if _names_a_metric(node.value)]
    assert found == [], "metric names belong in cdm/metric_names.py (read METRICS, CD, F1):\n" + "\n".join(found)
