"""A finished sweep's record (:func:`sweeps.store.read.read_sweep`) as the results stage reads it: its spec
validated, and one outcome per trial.

:func:`open_sweep` finds the sweep (the experiment's latest, or a given parent run), :func:`trial_records`
rebuilds each trial's outcome as the runner's results table reads it, and :func:`results_table` the
table itself; :func:`paper_layout` sets the cells out as the paper prints them (for the notebook).
The runner's end-of-sweep publishing and ``sweeps/results/publish.py`` are built on these; so is the notebook.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, fields
from functools import cached_property
from typing import Any

from mlflow.entities import Run
from pydantic import ValidationError

from cdm.config import format_validation_error
from cdm.metric_names import CD, METRICS
from sweeps.compare.outcomes import FINISHED, TrialOutcome, sweep_order, unstarted
from sweeps.compare.rules import settings_notes
from sweeps.compare.table import ResultsTable, build_table
from sweeps.execute.settle import Round, UntilSettled
from sweeps.plan.budget import parse_budget
from sweeps.plan.protocol import CARD_TAG
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import SpaceParam, Spec
from sweeps.plan.trials import SweepPlan, expand, split_label
from sweeps.store.read import LoggedSweep, last_objects, parent_baselines, read_sweep, trial_metrics

__all__ = [
    "SweepRecord",
    "TrialRecord",
    "open_sweep",
    "paper_layout",
    "protocol_card_lines",
    "results_table",
    "trial_records",
]

_STATUS = {"FINISHED": "ok", "FAILED": "failed"}
"""MLflow run status → :class:`TrialOutcome` status; RUNNING, SCHEDULED and KILLED runs never finished: pending."""


@dataclass(frozen=True)
class SweepRecord(LoggedSweep):
    """One sweep as MLflow holds it (:class:`sweeps.store.read.LoggedSweep`), its spec validated."""

    spec: Spec

    @property
    def profile(self) -> str:
        return self.parent.data.tags.get("profile", "?")

    @property
    def title(self) -> str:
        return f"{self.spec.name} — profile {self.profile}"

    @cached_property
    def expanded(self) -> SweepPlan:
        """The spec expanded again with the sweep's ``--set`` values, once per record: what a sequential
        sweep's rule reads (the pending rows and the table's stops both ask it)."""
        return expand(self.spec, self.profile, self.plan.get("sets", {}))


@dataclass(frozen=True)
class TrialRecord:
    """A trial's outcome (as the results table reads it) with what the plots and panels need besides."""

    outcome: TrialOutcome
    values: dict[str, Any]
    """Swept config values (grid cell or Optuna sample), dotted keys."""
    run_id: str | None
    """Its child run; None for a grid cell that never started."""


def open_sweep(uri: str, experiment: str | None = None, parent_run_id: str | None = None) -> SweepRecord:
    """The latest sweep of ``experiment`` (or the sweep whose parent run is ``parent_run_id``).

    Raises:
        sweeps.store.read.ReportError: no such experiment or sweep, or its spec/plan is missing or unreadable.
        SpecError: the spec it started with no longer validates.
    """
    logged = read_sweep(uri, experiment, parent_run_id)
    try:
        spec = Spec.model_validate(logged.spec_file)
    except ValidationError as exc:
        raise SpecError(f"sweep run {logged.parent.info.run_id}'s spec: {format_validation_error(exc, Spec)}") from None
    return SweepRecord(**{f.name: getattr(logged, f.name) for f in fields(logged)}, spec=spec)


def _sampled(run: Run, space: dict[str, SpaceParam]) -> dict[str, Any]:
    """An Optuna trial's sampled values, cast back from MLflow's string params by the space's types."""
    out: dict[str, Any] = {}
    for key, param in space.items():
        text = run.data.params.get(key)
        if text is None:
            continue
        if param.type == "categorical":
            out[key] = next((c for c in param.choices or [] if str(c) == text), text)
        else:
            out[key] = int(float(text)) if param.type == "int" else float(text)
    return out


def trial_records(record: SweepRecord, objects: bool = True) -> list[TrialRecord]:
    """Every trial of the sweep in the runner's order (grid: the plan's; Optuna: best first).

    With ``objects``, finished trials carry their last evaluation's per-object rows, so the results
    table gets its paired columns (one artifact download per trial).
    """
    cells = {c["label"]: c for c in record.plan.get("cells", [])}
    metric, mode = record.spec.metric.name, record.spec.metric.mode
    out = []
    for run in record.children:
        tags, label = run.data.tags, run.info.run_name
        status = _STATUS.get(run.info.status, "pending")
        if status == "ok" and tags.get("stopped_early") == "true":
            status = "stopped"
        planned = cells.get(label, {})
        # A trial that died before opening its run has only the name the driver gave it: `<cell> · seed <n>`.
        cell = tags.get("cell") or split_label(label)[0]
        values = planned.get("values") or _sampled(run, record.spec.search.space)
        # Baselines live on the parent run, once per evaluation set (older sweeps: on every child).
        metrics = parent_baselines(record.parent.data.metrics, tags.get("eval_set"), record.parent.data.params) | {
            k: v for k, v in trial_metrics(run.data.metrics, run.data.params).items() if "/" in k}
        rows = tuple(last_objects(record.client, run.info.run_id)) if objects and status in FINISHED else ()
        outcome = TrialOutcome(label, cell, status, metrics, _paper_label(record, planned), planned.get("paper") or {},
                               tags.get("error") if status == "failed" else None, rows,
                               record.expanded.f1_threshold(label, run.data.params))
        out.append(TrialRecord(outcome, values, run.info.run_id))
    if not record.spec.search.sampled:
        outcomes = [t.outcome for t in out]
        next_round = _final_round(record, outcomes).start if record.spec.sequential is not None else None
        for label in unstarted(list(cells), outcomes, next_round):
            c = cells[label]
            f1_threshold = record.expanded.f1_threshold(label, {})
            out.append(TrialRecord(TrialOutcome(label, split_label(label)[0], "pending", {}, _paper_label(record, c),
                                                c.get("paper") or {}, f1_threshold=f1_threshold), c["values"], None))
    key = sweep_order(list(cells) if not record.spec.search.sampled else None, metric, mode)
    return sorted(out, key=lambda t: key(t.outcome))


def _paper_label(record: SweepRecord, planned: dict[str, Any]) -> str | None:
    """The paper row's label for a planned cell: the row whose numbers it carries."""
    paper = record.spec.paper
    if paper is None or not planned.get("paper"):
        return None
    return next((r.label for r in paper.rows if r.values == planned["paper"]), None)


def _settings(record: SweepRecord) -> list[str]:
    """The runner's notes (:func:`sweeps.compare.rules.settings_notes`) from what MLflow recorded: the
    profile's budget on the parent run, each trial's resolved prediction target and λ in its params, and its
    machine in its tags."""
    plan = record.plan
    trials = [(r.data.params["diffusion.prediction"], float(r.data.params["priors.lambda_3d"]))
              for r in record.children if {"diffusion.prediction", "priors.lambda_3d"} <= r.data.params.keys()]
    return settings_notes(record.spec, record.profile, record.parent.data.params.get("steps", "?"),
                          plan.get("fixed", {}), plan.get("sets", {}), protocol_card_lines(record), trials,
                          [r.data.tags for r in record.children], record.parent.data.params.get("compute_s"))


def protocol_card_lines(record: SweepRecord) -> list[str]:
    """The sweep's protocol card (``sweeps/plan/protocol.py``) as the runner tagged it on the parent run; a
    sweep from before the card existed says it has none."""
    card = record.parent.data.tags.get(CARD_TAG)
    return card.splitlines() if card else ["no protocol card recorded (a sweep from before the card)"]


def _final_round(record: SweepRecord, outcomes: list[TrialOutcome]) -> Round:
    """A sequential sweep's rule on its recorded outcomes, as its searcher last applied it."""
    budget = record.parent.data.params.get("budget")
    return UntilSettled(record.expanded, parse_budget(budget) if budget else None).final(outcomes,
                                                                                        record.parent.data.tags)


def results_table(record: SweepRecord, trials: list[TrialRecord]) -> ResultsTable:
    """The runner's results table (same columns and notes, paired Δ where per-object rows are present)."""
    spec = record.spec
    outcomes = [t.outcome for t in trials]
    settled = None
    if (
        spec.sequential is not None
    ):  # where each cell stopped, as the runner's searcher decided (sweeps/execute/settle/)
        settled = _final_round(record, outcomes).records
    return build_table(outcomes, spec.metric.name, spec.metric.mode, record.title,
                       f"{spec.paper.table}: {spec.paper.note}" if spec.paper else "", compare_to=spec.compare_to,
                       settings=_settings(record), settled=settled)


def paper_layout(trials: list[TrialRecord]):
    """The ablation as the paper prints it: one row per cell, CD and F1 for all objects and per category,
    ours (mean over finished seeds) beside the paper's number.

    Returns:
        A ``pandas.DataFrame`` indexed by cell, with two-level columns: ``("", "paper setting")``,
        ``("", "trials")``, then ``(group, "CD ours" | "CD paper" | "F1 ours" | "F1 paper")`` for
        group ``all`` and each category we evaluated (the paper's value where it reports that category).
        Columns empty in every row are left out.
    """
    import pandas as pd

    keys = {k for t in trials for k in t.outcome.metrics}
    groups = ["all", *sorted({k.split("/")[2] for k in keys if k.startswith(f"{CD.key}/")})]
    cells: dict[str, list[TrialOutcome]] = {}
    for t in trials:
        cells.setdefault(t.outcome.cell, []).append(t.outcome)
    rows = {}
    for name, group in cells.items():
        done = [o for o in group if o.finished]
        failed = sum(o.status == "failed" for o in group)
        row: dict[tuple[str, str], Any] = {
            ("", "paper setting"): group[0].paper_label or "",
            ("", "trials"): f"{len(done)}/{len(group)}" + (f" ({failed} failed)" if failed else ""),
        }
        for g in groups:
            for short in METRICS:
                key = f"eval/{short}" + ("" if g == "all" else f"/{g}")
                values = [o.metrics[key] for o in done if key in o.metrics and math.isfinite(o.metrics[key])]
                row[(g, f"{short.upper()} ours")] = statistics.fmean(values) if values else math.nan
                row[(g, f"{short.upper()} paper")] = group[0].paper.get(key, math.nan)
        rows[name] = row
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.columns = pd.MultiIndex.from_tuples(table.columns)
    table.index.name = "cell"
    return table.dropna(axis=1, how="all")
