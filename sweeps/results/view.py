"""The runs view the runner links at the end of a sweep: the answer on MLflow's first screen.

At 1,280 × 800 with MLflow 3's default panels (the navigation on the left, the Assistant on the right)
the runs table shows its run names, the pinned "Created" column and about 285 px more. So the view
(:func:`share_view`) puts there, in this order: the sweep's metric and its partner (``final/f1``,
``final/cd``), then the tag ``vs reference``: the verdict against the reference cell and the 95 %
interval of Δ (``unclear [−0.006, +0.017] Δf1 +0.006``). The baselines are rows of the same view (runs tagged
``kind=baseline``), and the rows are sorted by the metric, so where each cell stands against them reads
off the order. The view shows the runs tagged ``sweep=<parent run id>``: the sweep's trials and its
baseline rows, which are no children of the parent (every reader of a sweep's children sees trials
only). One row per run: cells are grouped only when they have several seeds.
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter

from mlflow.entities import Metric

from sweeps.compare.rules import headline
from sweeps.compare.table import ResultsTable
from sweeps.results.sweep import SweepRecord

__all__ = ["BASELINE_KIND", "VERDICT_WORDS", "baseline_rows", "headline_name", "row_tags", "share_view", "sort_key"]

BASELINE_KIND = "baseline"
"""The ``kind`` tag of a baseline's row in the view: a run of the sweep (tag ``sweep``) that is no trial."""

VERDICT_WORDS = {"no clear difference": "unclear"}
"""A verdict as the ``vs reference`` column writes it: short enough that its interval stays on screen."""

_WIDTHS = {"metric": 60, "vs reference": 250, "vs baselines": 300}
"""Column widths (px) of the view: two scores and ``vs reference`` fill the ~285 px + scroll MLflow leaves."""


def sort_key(text: str) -> float | None:
    """A swept param's value as a number the runs view can sort by, or None when it is not one.

    MLflow orders params as text (``10`` before ``2``, ``1e-3`` after ``0.5``) but metrics as numbers,
    so :func:`share_view` logs this as the metric ``swept/<param>``."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def row_tags(table: ResultsTable, cell: str, metric: str) -> dict[str, str]:
    """The tags a cell's runs show as the view's columns: ``vs reference`` (verdict, interval of Δ, Δ)
    and ``vs baselines`` (the baselines it beats); empty for a cell the table did not pair."""
    record, diff = table.record(cell), table.difference(cell, metric)
    if table.reference is None or not record:
        return {}
    verdict = str(record.get("verdict") or "")
    verdict = VERDICT_WORDS.get(verdict, verdict)
    if cell == table.reference:
        versus = "reference"
    elif diff is None:
        versus = verdict or "no result"
    else:
        mean, interval = diff.text().split(" ", 1)
        versus = f"{verdict} {interval} Δ{metric.removeprefix('eval/')} {mean}"
    beaten = str(record.get("beats baselines") or "").replace(";", ", ")
    return {"vs reference": versus, "vs baselines": f"beats {beaten or 'none'}"}


def baseline_rows(record: SweepRecord, table: ResultsTable) -> list[str]:
    """One finished run per baseline of ``table`` in the sweep's view (tags ``sweep=<parent run id>``,
    ``kind=baseline``; named ``baseline: <name>``) holding its ``final/…`` scores; made once, found again
    on a second publish. Returns their run ids."""
    client, parent = record.client, record.parent.info.run_id
    found = {r.info.run_name: r.info.run_id for r in client.search_runs(
        [record.experiment_id], f"tags.sweep = '{parent}' and tags.kind = '{BASELINE_KIND}'")}
    out = []
    for row in (r for r in table.records if str(r["cell"]).startswith("baseline: ")):
        name = str(row["cell"])
        if name not in found:
            note = (f"The trivial baseline {name.removeprefix('baseline: ')}, scored on the sweep's held-out objects "
                    "(`cdm/evaluate.py`): what a cell's number is worth.")
            run_id = client.create_run(record.experiment_id, run_name=name, tags={
                "sweep": parent, "kind": BASELINE_KIND, "vs reference": BASELINE_KIND, "mlflow.note.content": note,
            }).info.run_id
            now, means = int(time.time() * 1000), {final: row.get(f"{m} mean") for m, final in _finals(record).items()}
            client.log_batch(run_id, metrics=[Metric(k, float(v), now, 0) for k, v in means.items() if v is not None])
            client.set_terminated(run_id)
            found[name] = run_id
        out.append(found[name])
    return out


def _finals(record: SweepRecord) -> dict[str, str]:
    """The sweep's metric and its partner (where an evaluation's) → the key the view shows it by: ``final/f1``."""
    return {m: "final/" + m.removeprefix("eval/") for m in headline(record.spec.metric.name) if m.startswith("eval/")}


def headline_name(record: SweepRecord, table: ResultsTable) -> str:
    """The parent run's name once the sweep has its answer: spec, profile and the table's headline
    (MLflow puts a run's name on top of its page, above everything else)."""
    return f"{record.spec.name} · {record.profile}: {table.headline}"[:250]


def share_view(record: SweepRecord, table: ResultsTable | None = None) -> str:
    """Save the runs view of this sweep (the module says what it shows) and return its path on the UI server
    (``#/experiments/…``): MLflow's own "shared view", an experiment tag ``mlflow.sharedViewState.<key>`` the UI
    reads. Its columns after the scores and ``vs reference``/``vs baselines`` (:func:`row_tags`): the swept values
    (a field whose values are all numbers as the metric ``swept/<field>``, :func:`sort_key`, logged here on each
    child) and the seed; a cell's seeds grouped by the tag ``group`` (their swept values), the row their average."""
    metric, mode = record.spec.metric.name, record.spec.metric.mode
    trials, parent = record.children, record.parent.info.run_id
    swept = list(
        dict.fromkeys([*record.spec.search.space, *(k for c in record.plan.get("cells", []) for k in c["values"])])
    )
    numeric = [k for k in swept if all(sort_key(r.data.params[k]) is not None for r in trials if k in r.data.params)]
    now = int(time.time() * 1000)
    for run in trials:
        if run.data.tags.get("sweep") != parent:
            record.client.set_tag(run.info.run_id, "sweep", parent)
        keys = [k for k in numeric if k in run.data.params and f"swept/{k}" not in run.data.metrics]
        if keys:
            record.client.log_batch(
                run.info.run_id, metrics=[Metric(f"swept/{k}", sort_key(run.data.params[k]), now, 0) for k in keys]
            )
    if table is not None:
        baseline_rows(record, table)
    finals = list(_finals(record).values())
    columns = (
        [f"metrics.`{m}`" for m in finals or [metric]]
        + ["tags.`vs reference`", "tags.`vs baselines`"]
        + [f"metrics.`swept/{k}`" for k in numeric]
        + [f"params.`{k}`" for k in swept if k not in numeric]
        + ["tags.`seed`"]
    )
    widths = {c: _WIDTHS["metric"] for c in columns if c.startswith("metrics.")}
    widths |= {f"tags.`{k}`": _WIDTHS[k] for k in ("vs reference", "vs baselines")}
    state: dict[str, object] = {
        "searchFilter": f"tags.sweep = '{parent}'",
        "selectedColumns": columns, "columnOrder": columns, "columnWidths": widths,
        "orderByKey": f"metrics.`{finals[0] if finals else metric}`", "orderByAsc": mode == "min",
    }
    seeds = Counter(run.data.tags.get("cell", run.info.run_name) for run in trials)
    if max(seeds.values(), default=1) > 1:
        # Grouped by the swept values alone (sweeps older than the `group` tag: by the full cell name).
        group = "group" if any("group" in r.data.tags for r in trials) else "cell"
        state["groupBy"] = {"aggregateFunction": "average", "groupByKeys": [{"mode": "tag", "groupByData": group}]}
    key = f"sweep-{parent}"
    record.client.set_experiment_tag(record.experiment_id, f"mlflow.sharedViewState.{key}", json.dumps(state))
    return f"#/experiments/{record.experiment_id}/runs?viewStateShareKey={key}"
