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

from cdm.metric_names import partner
from sweeps.compare.bootstrap import interval_text
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
    record = next((r for r in table.records if r["cell"] == cell), None)
    if record is None or f"{metric} delta" not in record:
        return {}
    short = metric.removeprefix("eval/")
    delta, low, high = (record.get(f"{metric} delta{end}") for end in ("", " low", " high"))
    verdict = str(record.get("verdict") or "")
    column = next(i for i, h in enumerate(table.header) if h.startswith(f"Δ{short} vs "))
    if table.rows[table.records.index(record)][column] == "reference":
        versus = "reference"
    elif delta is None:
        versus = VERDICT_WORDS.get(verdict, verdict) or "no result"
    else:
        mean, interval = interval_text(float(delta), float(low), float(high)).split(" ", 1)
        versus = f"{VERDICT_WORDS.get(verdict, verdict)} {interval} Δ{short} {mean}"
    beaten = str(record.get("beats baselines") or "").replace(";", ", ")
    return {"vs reference": versus, "vs baselines": f"beats {beaten or 'none'}"}


def baseline_rows(record: SweepRecord, table: ResultsTable) -> list[str]:
    """One finished run per baseline of ``table`` in the sweep's view (tags ``sweep=<parent run id>``,
    ``kind=baseline``; named ``baseline: <name>``) holding its ``final/…`` scores; made once, found again
    on a second publish. Returns their run ids."""
    client, parent = record.client, record.parent.info.run_id
    found = {r.info.run_name: r.info.run_id for r in client.search_runs(
        [record.experiment_id], f"tags.sweep = '{parent}' and tags.kind = '{BASELINE_KIND}'")}
    shown = [m for m in (record.spec.metric.name, partner(record.spec.metric.name)) if m and m.startswith("eval/")]
    out = []
    for row in (r for r in table.records if str(r["cell"]).startswith("baseline: ")):
        name = str(row["cell"])
        if name not in found:
            run_id = client.create_run(
                record.experiment_id,
                run_name=name,
                tags={
                    "sweep": parent,
                    "kind": BASELINE_KIND,
                    "vs reference": BASELINE_KIND,
                    "mlflow.note.content": f"The trivial baseline {name.removeprefix('baseline: ')}, "
                    "scored on the sweep's "
                    "held-out objects (`cdm/evaluate.py`): what a cell's number is worth.",
                },
            ).info.run_id
            now = int(time.time() * 1000)
            client.log_batch(
                run_id,
                metrics=[
                    Metric("final/" + m.removeprefix("eval/"), float(row[f"{m} mean"]), now, 0)
                    for m in shown
                    if row.get(f"{m} mean") is not None
                ],
            )
            client.set_terminated(run_id)
            found[name] = run_id
        out.append(found[name])
    return out


def headline_name(record: SweepRecord, table: ResultsTable) -> str:
    """The parent run's name once the sweep has its answer: spec, profile and the table's headline
    (MLflow puts a run's name on top of its page, above everything else)."""
    head = table.summary[0] if table.summary else "no cell finished a trial"
    return f"{record.spec.name} · {record.profile}: {head}"[:250]


def share_view(record: SweepRecord, table: ResultsTable | None = None) -> str:
    """Save the runs view of this sweep and return its path on the UI server (``#/experiments/…``).

    The view (MLflow's own "shared view": an experiment tag ``mlflow.sharedViewState.<key>`` the UI
    reads) lists the sweep's child runs (each tagged ``sweep`` here) and its baseline rows
    (:func:`baseline_rows`, with ``table``),
    sorted by the metric, with ``final/<metric>``, its partner, ``vs reference`` (:func:`row_tags`),
    ``vs baselines``, the swept values and the seed as columns in that order. A swept field whose
    values are all numbers is shown as the metric ``swept/<field>`` (:func:`sort_key`, logged here on
    each child). Cells with several seeds are grouped by the tag ``group`` (their swept values): the
    group row averages the seeds."""
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
    finals = ["final/" + m.removeprefix("eval/") for m in (metric, partner(metric)) if m and m.startswith("eval/")]
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
