"""The metric record (:mod:`cdm.metric_names`) is the one home of every metric: no other module of ``cdm/`` or
``sweeps/`` spells a metric's name (``"cd"``, ``"eval/f1"``, ``f"baseline/{b}/cd"``) in its code, and a metric
declared there alone reaches MLflow, the results table, the verdicts and the report."""

from __future__ import annotations

import ast
import csv
from pathlib import Path

import pytest
import torch
from mlflow import MlflowClient

from cdm.metric_names import METRICS, Metric, declare
from cdm.metrics import scores
from sweeps.results import publish
from sweeps.results.sweep import open_sweep, results_table, trial_records
from tests.test_publish import _start, _trial

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


SPREAD = """name: spread
grid: {priors.point_size: [0.02, 0.04]}
metric: {name: eval/spread, mode: min}
"""


@pytest.fixture
def spread():
    """A dummy metric declared in the record for one test: the mean distance of the predicted points from their
    centre (world units), better lower."""
    radius = Metric("spread", lambda pred, gt, _: (pred - pred.mean(1, keepdim=True)).norm(dim=-1).mean(1), "min",
                    lambda _: "mean radius, world units")
    yield declare(radius)
    METRICS.pop(radius.name)


def _star(radii: list[float]) -> torch.Tensor:
    """``(B, 6, 3)``: per shape the six points ±r on the axes, whose spread is exactly r."""
    axes = torch.cat([torch.eye(3), -torch.eye(3)])
    return torch.stack([axes * r for r in radii])


def test_a_metric_declared_in_the_record_reaches_mlflow_the_table_the_verdicts_and_the_report(spread, tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep, plan = _start(tmp_path, uri, SPREAD)
    gt = _star([0.5, 0.5, 0.5])
    for i, cell in enumerate(plan.cells):
        per_shape = scores(_star([0.5 + 0.25 * i, 0.75 + 0.25 * i, 1.0 + 0.25 * i]), gt)
        assert per_shape["spread"] == pytest.approx([0.5 + 0.25 * i, 0.75 + 0.25 * i, 1.0 + 0.25 * i])
        objects = [{"object_id": f"o{k}", "category": "chair", "eval_set": "e1",
                    **{name: v[k] for name, v in per_shape.items()}} for k in range(3)]
        last = {f"eval/{name}": sum(v) / 3 for name, v in per_shape.items()}
        _trial(tmp_path, sweep, f"t{i}", cell.label, cell.values, {20: last}, objects)
        sweep.close_trial(f"t{i}", cell.label, "FINISHED", last=last)
    sweep.end()
    client = MlflowClient(uri)
    runs = {r.info.run_name: r.data.metrics
            for r in client.search_runs([sweep.experiment_id], f"tags.mlflow.parentRunId = '{sweep.run_id}'")}
    assert runs["point_size=0.04 · seed 0"]["final/spread"] == pytest.approx(1.0)
    assert runs["point_size=0.02 · seed 0"]["eval/spread"] == pytest.approx(0.75)

    record = open_sweep(uri, "spread")
    table = results_table(record, trial_records(record))
    rows = {r["cell"]: r for r in table.records}
    assert rows["point_size=0.02"]["eval/spread mean"] == pytest.approx(0.75)
    # Paired on objects.csv's spread column: each object 0.25 wider, worse where lower is better.
    assert rows["point_size=0.04"]["eval/spread delta"] == pytest.approx(0.25)
    assert rows["point_size=0.04"]["verdict"].startswith("worse")

    out = tmp_path / "report"
    assert publish.main(["spread", "--tracking-uri", uri, "--out", str(out)]) == 0
    report = list(csv.DictReader((out / "results.csv").open()))
    assert [float(r["eval/spread mean"]) for r in report] == pytest.approx([0.75, 1.0])
    described = publish.describe_trial(record, trial_records(record)[0], table)
    assert "eval/spread (mean radius, world units) 0.75" in described
