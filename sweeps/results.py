"""The results table of a sweep: one row per cell, mean ± std over seeds, the paper's number beside it.

Knows nothing of Ray or MLflow: the runner turns finished trials into :class:`TrialOutcome` s and
this module aggregates and formats them — plain text for the terminal, Markdown and CSV for the
sweep folder. Trivial baselines the trainer reports (``baseline/<name>/<metric>``: sphere, Gaussian,
category mean) get their own rows, so a local result is never read without them (NOTES §6).
"""

from __future__ import annotations

import csv
import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

__all__ = ["ResultsTable", "TrialOutcome", "build_table"]

Status = Literal["ok", "stopped", "failed", "pending"]


@dataclass(frozen=True)
class TrialOutcome:
    """How one trial ended and its last evaluation's metrics."""

    label: str
    """Unique trial label (the MLflow run name)."""
    cell: str
    """Cell name; trials of one cell at different seeds are aggregated."""
    status: Status
    """``ok`` ran to the end, ``stopped`` early by the scheduler, ``failed`` raised, ``pending`` never ran."""
    metrics: dict[str, float] = field(default_factory=dict)
    paper_label: str | None = None
    paper: dict[str, float] = field(default_factory=dict)
    error: str | None = None


@dataclass(frozen=True)
class _Stat:
    mean: float
    std: float | None
    n: int

    @classmethod
    def of(cls, values: Sequence[float]) -> _Stat | None:
        values = [v for v in values if math.isfinite(v)]
        if not values:
            return None
        return cls(statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None, len(values))

    def text(self) -> str:
        return _num(self.mean) + ("" if self.std is None else f" ± {_num(self.std, self.mean)}")


def _num(value: float, scale: float | None = None) -> str:
    """3 decimals for F1-like numbers, 2 for CD ×1000-like ones (decided by ``scale``, default ``value``)."""
    return f"{value:.3f}" if abs(value if scale is None else scale) < 10 else f"{value:.2f}"


@dataclass(frozen=True)
class ResultsTable:
    """Formatted rows (``header`` columns) plus per-column numbers for the CSV."""

    title: str
    header: list[str]
    rows: list[list[str]]
    records: list[dict[str, object]]
    """One flat record per row for the CSV: means, stds, counts and paper values as numbers."""
    notes: list[str]
    best: str | None

    def text(self) -> str:
        widths = [max(len(r[i]) for r in [self.header, *self.rows]) for i in range(len(self.header))]
        line = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()
        out = [self.title, line(self.header), "  ".join("-" * w for w in widths)]
        out += [line(r) for r in self.rows] + self.notes
        return "\n".join(out)

    def markdown(self) -> str:
        out = [f"## {self.title}", "", "| " + " | ".join(self.header) + " |", "|" + "---|" * len(self.header)]
        out += ["| " + " | ".join(r) + " |" for r in self.rows]
        out += [""] + [f"- {n}" for n in self.notes]
        return "\n".join(out) + "\n"

    def write(self, folder: str | Path) -> tuple[Path, Path]:
        """Write ``results.md`` and ``results.csv`` into ``folder``; returns their paths."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        md, table = folder / "results.md", folder / "results.csv"
        md.write_text(self.markdown())
        keys = list(dict.fromkeys(k for r in self.records for k in r))
        with table.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=keys)
            writer.writeheader()
            writer.writerows(self.records)
        return md, table


def _partner(metric: str) -> str | None:
    """``eval/f1`` ↔ ``eval/cd``: the other headline metric, shown beside the optimised one."""
    swaps = {"/f1": "/cd", "/cd": "/f1"}
    for a, b in swaps.items():
        if metric.startswith("eval/") and metric.endswith(a) and metric.count("/") == 1:
            return metric[: -len(a)] + b
    return None


def _categories(outcomes: Sequence[TrialOutcome], metric: str) -> list[str]:
    prefix = metric + "/"
    return sorted({k[len(prefix):] for o in outcomes for k in o.metrics if k.startswith(prefix)})


def build_table(
    outcomes: Sequence[TrialOutcome],
    metric: str,
    mode: Literal["min", "max"],
    title: str,
    paper_note: str = "",
) -> ResultsTable:
    """Aggregate trials per cell (in first-seen order) and mark the best cell by ``metric``/``mode``."""
    cells: dict[str, list[TrialOutcome]] = {}
    for o in outcomes:
        cells.setdefault(o.cell, []).append(o)
    partner = _partner(metric)
    shown = [m for m in (metric, partner) if m is not None]
    categories = _categories(outcomes, metric)
    has_paper_label = any(o.paper_label for o in outcomes)
    header = ["cell"] + (["paper setting"] if has_paper_label else []) + ["trials"]
    for m in shown:
        header += [m, f"paper {m}"]
    header += [f"{metric}/{c}" for c in categories]

    stats = {name: _Stat.of([o.metrics[metric] for o in group if o.status in ("ok", "stopped") and metric in o.metrics])
             for name, group in cells.items()}
    ranked = [(s.mean, name) for name, s in stats.items() if s is not None]
    best = (min(ranked) if mode == "min" else max(ranked))[1] if ranked else None

    rows: list[list[str]] = []
    records: list[dict[str, object]] = []
    for name, group in cells.items():
        first = group[0]
        counts = {s: sum(o.status == s for o in group) for s in ("ok", "stopped", "failed", "pending")}
        trials = f"{counts['ok'] + counts['stopped']}/{len(group)}" + "".join(
            f" ({counts[s]} {s})" for s in ("stopped", "failed", "pending") if counts[s])
        row = [name + (" ★" if name == best else "")] + ([first.paper_label or ""] if has_paper_label else []) + [trials]
        record: dict[str, object] = {"cell": name, "paper_setting": first.paper_label or "", "best": name == best, **counts}
        done = [o for o in group if o.status in ("ok", "stopped")]
        for m in shown + [f"{metric}/{c}" for c in categories]:
            stat = _Stat.of([o.metrics[m] for o in done if m in o.metrics])
            paper = first.paper.get(m)
            text = "failed" if stat is None and counts["failed"] else ("–" if stat is None else stat.text())
            if m in shown:
                row += [text, "" if paper is None else _num(paper)]
            else:
                row.append(text + ("" if paper is None else f" ({_num(paper)})"))
            record.update({f"{m} mean": stat.mean if stat else None, f"{m} std": stat.std if stat else None,
                           f"{m} paper": paper})
        rows.append(row)
        records.append(record)

    suffix = metric.removeprefix("eval/") if metric.startswith("eval/") else None
    baselines = sorted({k.split("/")[1] for o in outcomes for k in o.metrics if k.startswith("baseline/")})
    for b in baselines if suffix else []:
        done = [o for o in outcomes if o.status in ("ok", "stopped")]
        # Baselines depend on the evaluation data only, not on the cell: their mean is the number.
        row = [f"baseline: {b}"] + ([""] if has_paper_label else []) + [""]
        record = {"cell": f"baseline: {b}"}
        for m in shown + [f"{metric}/{c}" for c in categories]:
            key = "baseline/" + b + "/" + m.removeprefix("eval/")
            stat = _Stat.of([o.metrics[key] for o in done if key in o.metrics])
            row += [_num(stat.mean) if stat else "–"] + ([""] if m in shown else [])
            record.update({f"{m} mean": stat.mean if stat else None})
        rows.append(row)
        records.append(record)

    notes = []
    if paper_note:
        notes.append(f"paper: {paper_note}")
    if categories:
        notes.append(f"{metric}/<category> columns: ours (paper) where the paper reports that category")
    if best is not None:
        notes.append(f"★ best cell by {metric} ({mode}); ± is the standard deviation over seeds")
    notes += [f"failed: {o.label} — {o.error or 'no reason recorded'}" for o in outcomes if o.status == "failed"]
    return ResultsTable(title, header, rows, records, notes, best)
