"""The results table of a sweep: one row per cell, mean ± std over seeds, the paper's number beside it.

Knows nothing of Ray or MLflow: the runner turns finished trials into :class:`TrialOutcome` s and
this module aggregates and formats them — plain text for the terminal, Markdown and CSV for the
sweep folder. Trivial baselines the trainer reports (``baseline/<name>/<metric>``: sphere, Gaussian,
category mean, retrieval) get their own rows, so a local result is never read without them (the
local recipes land near them: benchmarks/RESULTS.md, "Which recipe learns").

When trials carry their per-object scores, every cell (and every baseline) is also compared pairwise
with a reference cell (:mod:`sweeps.compare.paired`): mean difference, 95% bootstrap interval and a verdict,
plus which baselines the cell beats with an interval that excludes 0. A verdict weighs the metric
and its partner (``better on f1, worse on cd``); cells that ran until their comparison settled
(:mod:`sweeps.compare.sequential`) show their seeds, why they stopped, and an interval over seeds and objects.
"""

from __future__ import annotations

import csv
import io
import math
import textwrap
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from cdm.baseline_names import BASELINES
from sweeps.compare.paired import PairedDifference, UnpairedError, compare, per_object_means
from sweeps.compare.rules import F1_UNIT, Stat, number_text, object_column, partner, partner_mode, weighed
from sweeps.compare.sequential import FOOTNOTE as SETTLED_FOOTNOTE
from sweeps.compare.sequential import SettleRecord
from sweeps.storage import write_file

__all__ = ["FINISHED", "ResultsTable", "TrialOutcome", "build_table", "sweep_order", "unstarted"]

Status = Literal["ok", "stopped", "failed", "pending"]
FINISHED: tuple[Status, ...] = ("ok", "stopped")
"""Statuses whose trial has metrics to aggregate: ran to the end, or stopped early by the scheduler."""


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
    objects: tuple[dict[str, object], ...] = ()
    """Per-object rows of the last evaluation (``object_id``, ``category``, ``cd``, ``f1``, ``baseline/…``)."""

    @property
    def finished(self) -> bool:
        """Ran to the end or was stopped early: its last evaluation counts."""
        return self.status in FINISHED


def sweep_order(
    labels: Sequence[str] | None, metric: str, mode: Literal["min", "max"]
) -> Callable[[TrialOutcome], float]:
    """Sort key of a sweep's outcomes, as the runner and the report list them: a grid's trials in its
    plan's order ``labels`` (unplanned last); an Optuna sweep's (``labels`` None) best ``metric`` first."""
    if labels is not None:
        order = {label: i for i, label in enumerate(labels)}
        return lambda o: order.get(o.label, len(order))
    sign = 1 if mode == "min" else -1
    return lambda o: sign * o.metrics.get(metric, sign * math.inf)


def unstarted(
    planned: Sequence[str], outcomes: Iterable[TrialOutcome], next_round: Collection[str] | None = None
) -> list[str]:
    """Labels of a grid's ``planned`` trials with no outcome, in plan order: the rows an interrupted sweep
    lists as pending, the runner's table and the report's alike. ``next_round``: a sequential sweep's
    trials its rule would start next (:func:`sweeps.compare.settle.final_round`); the seeds it never
    needed are no trials of it."""
    seen = {o.label for o in outcomes}
    return [label for label in planned if label not in seen and (next_round is None or label in next_round)]


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
    summary: list[str] = field(default_factory=list)
    """One plain sentence per class of cells: how it stands against the baselines (and the failed ones)."""
    wide_only: frozenset[str] = frozenset()
    """Columns only ``results.md``/``.csv`` carry (per category, baselines beaten: the summary says it)."""
    narrowing: tuple[str, ...] = ()
    """Columns the terminal drops first, in this order, until the table fits its width."""
    answer: tuple[str, ...] = ()
    """The narrow table's columns (cell, metric, partner, Δ metric, verdict): the run page's first table."""

    def _filled(self, names: Sequence[str] | None = None) -> list[int]:
        """Indices of the columns named (default: all) that some row fills; the first column always."""
        return [i for i, h in enumerate(self.header)
                if (names is None or h in names) and (i == 0 or any(r[i] for r in self.rows))]

    def text(self, width: int = 120) -> str:
        """The table for a terminal, at most ``width`` columns: the wide columns stay in ``results.md``,
        empty ones are left out, then ``narrowing`` columns until it fits; notes are wrapped."""
        keep = [i for i in self._filled() if self.header[i] not in self.wide_only]

        def widths(columns: list[int]) -> list[int]:
            return [max(len(r[i]) for r in [self.header, *self.rows]) for i in columns]

        for name in self.narrowing:
            if sum(widths(keep)) + 2 * (len(keep) - 1) <= width:
                break
            keep = [i for i in keep if self.header[i] != name]
        sizes = widths(keep)

        def line(cells: list[str]) -> str:
            return "  ".join(cells[i].ljust(w) for i, w in zip(keep, sizes)).rstrip()

        out = [self.title, line(self.header), "  ".join("-" * w for w in sizes)] + [line(r) for r in self.rows]
        dropped = [h for i, h in enumerate(self.header) if i not in keep and any(r[i] for r in self.rows)]
        categories = [h for h in dropped if h.count("/") == 2]
        if categories:  # eval/f1/chair, eval/f1/lamp, … → eval/f1/<category>
            dropped[dropped.index(categories[0])] = categories[0].rsplit("/", 1)[0] + "/<category>"
            dropped = [h for h in dropped if h not in categories]
        notes = self.notes + (
            ["not shown here, in results.md and results.csv: " + ", ".join(dropped)] if dropped else []
        )
        out += [""] + [textwrap.fill(s, width) for s in self.summary] if self.summary else []
        out += [""] + [textwrap.fill(n, width, subsequent_indent="  ") for n in notes] if notes else []
        return "\n".join(out)

    def grid(self, names: Sequence[str] | None = None) -> str:
        """The rows as a Markdown table of the columns ``names`` (default: all), empty columns left out."""
        keep = self._filled(names)
        out = ["| " + " | ".join(self.header[i] for i in keep) + " |", "|" + "---|" * len(keep)]
        return "\n".join(out + ["| " + " | ".join(r[i] for i in keep) + " |" for r in self.rows])

    def markdown(self) -> str:
        out = [f"## {self.title}", "", self.grid(), ""] + [f"- {n}" for n in self.summary + self.notes]
        return "\n".join(out) + "\n"

    def write(self, folder: str | Path) -> tuple[Path, Path]:
        """Write ``results.md`` and ``results.csv`` into ``folder``; returns their paths."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        md, table = folder / "results.md", folder / "results.csv"
        write_file(md, self.markdown())  # a link planted at either name is refused, not written through
        rows = io.StringIO()
        writer = csv.DictWriter(rows, fieldnames=list(dict.fromkeys(k for r in self.records for k in r)))
        writer.writeheader()
        writer.writerows(self.records)
        write_file(table, rows.getvalue())
        return md, table


def _categories(outcomes: Sequence[TrialOutcome], metric: str) -> list[str]:
    prefix = metric + "/"
    return sorted({k[len(prefix):] for o in outcomes for k in o.metrics if k.startswith(prefix)})


def _finished(group: Sequence[TrialOutcome]) -> list[TrialOutcome]:
    return [o for o in group if o.finished]


def _object_scores(group: Sequence[TrialOutcome], key: str, category: str | None) -> dict[str, float]:
    """``object_id →`` score under ``key`` of a cell's finished trials, seeds averaged per object."""
    trials = [
        [r for r in o.objects if category is None or r["category"] == category] for o in _finished(group) if o.objects
    ]
    return per_object_means(trials, key) if trials and all(key in r for t in trials for r in t) else {}


@dataclass
class _Pairing:
    """Paired differences of every cell and baseline against the reference cell, per shown metric."""

    reference: str
    diffs: dict[tuple[str, str], PairedDifference | str]
    """``(row name, metric) →`` the difference, or why there is none."""
    against: dict[str, dict[str, str]]
    """Cell → baseline → weighed verdict of the cell against it (``better``: on the metric, not worse on the partner)."""
    verdicts: dict[str, str]
    """Cell → its weighed verdict against the reference cell; a settled cell's says after how many seeds."""
    settled: Mapping[str, SettleRecord]
    notes: list[str]

    @classmethod
    def build(cls, cells: dict[str, list[TrialOutcome]], reference: str, shown: list[str],
              mode: Literal["min", "max"], baselines: list[str], settled: Mapping[str, SettleRecord]) -> _Pairing:
        pairing = cls(reference, {}, {}, {}, {n: r for n, r in settled.items() if n in cells and n != reference}, [])
        metric, modes = shown[0], {m: mode if m == shown[0] else partner_mode(m) for m in shown}
        to_baseline: dict[tuple[str, str, str], str] = {}
        unpaired: list[str] = []
        for m in shown:
            column, category = object_column(m)  # type: ignore[misc]
            scores = {name: _object_scores(group, column, category) for name, group in cells.items()}
            for name, values in scores.items():
                if name == reference or not values:
                    continue
                try:
                    pairing.diffs[(name, m)] = compare(values, scores[reference], (name, reference))
                except UnpairedError:
                    pairing.diffs[(name, m)] = "not paired"
                    unpaired += [name] if m == metric else []
            for name, group in cells.items():
                for b in baselines:
                    # The baselines scored on this cell's own objects, whichever objects those are.
                    ours, theirs = scores[name], _object_scores(group, f"baseline/{b}/{column}", category)
                    if ours and set(ours) == set(theirs):
                        to_baseline[(name, b, m)] = compare(ours, theirs, (name, b)).verdict(modes[m])
        for (name, b, m), verdict in to_baseline.items():
            if m == metric:
                others = [(p, to_baseline[(name, b, p)]) for p in shown[1:] if (name, b, p) in to_baseline]
                pairing.against.setdefault(name, {})[b] = weighed([(m, verdict), *others])
        for name in cells:
            found = {
                m: d.verdict(modes[m]) for m in shown if isinstance(d := pairing.diffs.get((name, m)), PairedDifference)
            }
            record = pairing.settled.get(name)
            if record is not None:
                # The partner was not decided on: its interval over objects only, said as such.
                aside = [f" ({v} on {m.removeprefix('eval/')}, objects only)" for m, v in found.items()
                           if m != metric and v not in ("no clear difference", record.decision.verdict)]
                pairing.verdicts[name] = "".join([record.text(), *aside])
            elif metric in found:
                pairing.verdicts[name] = weighed(
                    [(metric, found[metric])] + [(m, v) for m, v in found.items() if m != metric]
                )
        if unpaired:
            pairing.notes.append(f"not paired with {reference}, evaluated on other objects or settings (a paired "
                                 f"comparison needs the same evaluation set): {', '.join(unpaired)}")
        return pairing

    def beats(self, name: str) -> list[str]:
        return [b for b, v in self.against.get(name, {}).items() if v == "better"]

    def delta(self, name: str, m: str, metric: str) -> PairedDifference | str | None:
        """Row ``name``'s Δ on ``m``: a settled cell's interval over seeds and objects on the metric, else the paired one."""
        record = self.settled.get(name)
        if record is not None and m == metric:
            i = record.decision.interval
            return PairedDifference(i.mean, i.low, i.high, i.objects)
        return self.diffs.get((name, m))

    def columns(self, name: str, shown: list[str], metric: str) -> list[str]:
        """A cell's Δ per shown metric, verdict and the baselines it beats."""
        out = []
        for m in shown:
            d = self.delta(name, m, metric)
            out.append(
                "reference" if name == self.reference else d.text() if isinstance(d, PairedDifference) else d or "–"
            )
        return out + [self.verdicts.get(name, ""), ", ".join(self.beats(name)) or "none"]


def build_table(
    outcomes: Sequence[TrialOutcome],
    metric: str,
    mode: Literal["min", "max"],
    title: str,
    paper_note: str = "",
    compare_to: str | None = None,
    settings: Sequence[str] = (),
    *,
    settled: Mapping[str, SettleRecord] | None = None,
) -> ResultsTable:
    """Aggregate trials per cell (in first-seen order) and star the best cell by ``metric``/``mode``
    when it is apart from the next at the printed precision (else the leaders are marked tied).

    With per-object rows on the trials, every cell and baseline is paired with ``compare_to``
    (default: the first cell): mean difference and 95% bootstrap interval for each shown metric, a
    verdict weighing ``metric`` and its partner, and the baselines the cell beats. ``settled`` (cell →
    where its run until settled stopped, from the sequential runner) adds a ``seeds`` column and puts
    that record's interval over seeds and objects, and its verdict, in the cell's row. ``settings``
    lines (what produced the numbers, e.g. the prediction target) head the notes.
    """
    cells: dict[str, list[TrialOutcome]] = {}
    for o in outcomes:
        cells.setdefault(o.cell, []).append(o)
    second = partner(metric)
    shown = [m for m in (metric, second) if m is not None]
    categories = _categories(outcomes, metric)
    has_paper_label = any(o.paper_label for o in outcomes)
    # In cdm.evaluate's order, weakest first (sphere … retrieval); any other after them.
    found = {k.split("/")[1] for o in outcomes for k in o.metrics if k.startswith("baseline/")}
    baselines = [b for b in BASELINES if b in found] + sorted(found - set(BASELINES))
    reference = compare_to or next(iter(cells), None)
    pairing = None
    if object_column(metric) is not None and reference in cells and any(o.objects for o in _finished(cells[reference])):
        pairing = _Pairing.build(cells, reference, shown, mode, baselines, settled or {})
    seeds_column = bool(pairing and pairing.settled)
    header = ["cell"] + (["paper setting"] if has_paper_label else []) + ["trials"] + ["seeds"] * seeds_column
    for m in shown:
        header += [m, f"paper {m}"]
    header += [f"{metric}/{c}" for c in categories]
    if pairing:
        header += [f"Δ{m.removeprefix('eval/')} vs {reference} [95% CI]" for m in shown] + [
            "verdict",
            "beats baselines",
        ]

    stats = {name: Stat.of([o.metrics[metric] for o in group if o.finished and metric in o.metrics])
             for name, group in cells.items()}
    ranked = sorted((s.mean if mode == "min" else -s.mean, name) for name, s in stats.items() if s is not None)
    # Cells that print the leader's mean: a star between them would rest on digits nobody sees.
    leaders = [name for _, name in ranked if number_text(stats[name].mean) == number_text(stats[ranked[0][1]].mean)]  # type: ignore[union-attr]
    best = leaders[0] if len(leaders) == 1 else None
    mark = {best: " ★"} if best else {name: " (tied)" for name in leaders}
    lead = _lead(cells, best, ranked[1][1], metric) if pairing and best and len(ranked) > 1 else None

    rows: list[list[str]] = []
    records: list[dict[str, object]] = []
    for name, group in cells.items():
        first = group[0]
        counts = {s: sum(o.status == s for o in group) for s in ("ok", "stopped", "failed", "pending")}
        trials = f"{counts['ok'] + counts['stopped']}/{len(group)}" + "".join(
            f" ({counts[s]} {s})" for s in ("stopped", "failed", "pending") if counts[s])
        row = [name + mark.get(name, "")] + ([first.paper_label or ""] if has_paper_label else []) + [trials]
        record: dict[str, object] = {
            "cell": name,
            "paper_setting": first.paper_label or "",
            "best": name == best,
            **counts,
        }
        if seeds_column:
            settle = pairing.settled.get(name)  # type: ignore[union-attr]
            row.append(f"{settle.seeds} ({settle.reason})" if settle else "")
            record.update({"seeds": settle.seeds if settle else None, "stop reason": settle.reason if settle else ""})
        done = _finished(group)
        for m in shown + [f"{metric}/{c}" for c in categories]:
            stat = Stat.of([o.metrics[m] for o in done if m in o.metrics])
            paper = first.paper.get(m)
            text = "failed" if stat is None and counts["failed"] else ("–" if stat is None else stat.text())
            if m in shown:
                row += [text, "" if paper is None else number_text(paper)]
            else:
                row.append(text + ("" if paper is None else f" ({number_text(paper)})"))
            record.update({f"{m} mean": stat.mean if stat else None, f"{m} std": stat.std if stat else None,
                           f"{m} paper": paper})
        if pairing:
            row += pairing.columns(name, shown, metric)
            record.update(_paired_record(pairing, name, shown, metric))
        rows.append(row)
        records.append(record)

    suffix = metric.removeprefix("eval/") if metric.startswith("eval/") else None
    for b in baselines if suffix else []:
        done = _finished(outcomes)
        # Baselines depend on the evaluation data only, not on the cell: their mean is the number.
        row = [f"baseline: {b}"] + ([""] if has_paper_label else []) + [""] + [""] * seeds_column
        record = {"cell": f"baseline: {b}"}
        for m in shown + [f"{metric}/{c}" for c in categories]:
            key = "baseline/" + b + "/" + m.removeprefix("eval/")
            stat = Stat.of([o.metrics[key] for o in done if key in o.metrics])
            row += [number_text(stat.mean) if stat else "–"] + ([""] if m in shown else [])
            record.update({f"{m} mean": stat.mean if stat else None})
        if pairing:  # a reference row: no difference to the reference cell, no verdict
            row += [""] * (len(shown) + 2)
        rows.append(row)
        records.append(record)

    notes = list(settings)
    notes += [F1_UNIT] if any(m.split("/")[1:2] == ["f1"] for m in shown) else []
    if paper_note:
        notes.append(f"paper: {paper_note}")
    if any(f"{metric}/{c}" in o.paper for o in outcomes for c in categories):
        notes.append(f"{metric}/<category> columns: ours (paper) where the paper reports that category")
    seeds = max((len(_finished(group)) for group in cells.values()), default=0)
    if ranked:
        star = (f"★ highest mean {metric} ({mode}), apart from the next at the printed precision; \"best\" only where "
                f"its paired interval against the next cell excludes 0" if best else
                f"no ★: {', '.join(leaders)} tied for best by {metric} ({mode}) at the printed precision")
        notes.append(star + ("; ± is the standard deviation over seeds" if seeds > 1 else ""))
    if pairing:
        weighed = f"{metric} ({mode})" + (f" and {second} ({partner_mode(second)})" if second else "")
        notes.append(f"Δ: mean over the same objects of (row − {reference}), seeds averaged per object, with a 95% "
                     f"paired bootstrap interval over the objects; verdict and beats baselines by {weighed}, interval "
                     f"excluding 0 (a verdict names each metric when they disagree)")
        notes.append("the bootstrap intervals cover the held-out objects only, not training seeds: "
                     + ("with one seed per cell, another seed can move a cell by more than an interval's width"
                        if seeds == 1 else "the seeds are averaged, their spread is not in the interval"))
        notes += [SETTLED_FOOTNOTE] if seeds_column else []
        notes += pairing.notes
    notes += [f"failed: {o.label} — {o.error or 'no reason recorded'}" for o in outcomes if o.status == "failed"]
    narrowing = [f"Δ{second.removeprefix('eval/')} vs {reference} [95% CI]"] if pairing and second else []
    narrowing += ["paper setting"] + ([f"paper {second}", second] if second else [])
    answer = ("cell", *["seeds"] * seeds_column, *shown,
              *([f"Δ{metric.removeprefix('eval/')} vs {reference} [95% CI]", "verdict"] if pairing else []))
    return ResultsTable(
        title,
        header,
        rows,
        records,
        notes,
        best,
        _summary(cells, stats, leaders, metric, pairing, lead, mode),
        frozenset([f"{metric}/{c}" for c in categories] + ["beats baselines"]),
        tuple(narrowing),
        answer,
    )


def _lead(cells: dict[str, list[TrialOutcome]], best: str, runner_up: str, metric: str) -> PairedDifference | None:
    """The leader ``best`` against the next cell ``runner_up`` on ``metric``, paired per object; None if unpaired."""
    ours, theirs = (_object_scores(cells[n], *object_column(metric)) for n in (best, runner_up))  # type: ignore[misc]
    return compare(ours, theirs, (best, runner_up)) if ours and theirs and set(ours) == set(theirs) else None


def _baseline_name(name: str) -> str:
    return {"gaussian": "Gaussian"}.get(name, name.replace("_", " "))


def _summary(
    cells: dict[str, list[TrialOutcome]],
    stats: dict[str, Stat | None],
    leaders: list[str],
    metric: str,
    pairing: _Pairing | None,
    lead: PairedDifference | None = None,
    mode: Literal["min", "max"] = "max",
) -> list[str]:
    """One sentence per class of cells — the best cell (only when ``lead``, its paired Δ to the next, excludes 0;
    else the leader, said not resolvable), then cells that stand the same against the baselines (weighed
    verdicts), then every cell's verdict against the reference cell — and one for those with no result."""
    if not leaders:
        return ["no cell finished a trial"] if cells else []

    def standing(name: str, plural: bool) -> str:
        against = (pairing.against if pairing else {}).get(name)
        if not against:
            return f"{metric} {stats[name].text()}" if stats[name] else "no result"  # type: ignore[union-attr]
        words = {"better": "beat" if plural else "beats", "no clear difference": "level with", "worse": "below"}
        by_verdict: dict[str, list[str]] = {}
        for b, v in against.items():
            by_verdict.setdefault(v, []).append(_baseline_name(b))
        ordered = [v for v in words if v in by_verdict] + [v for v in by_verdict if v not in words]
        return "; ".join(
            f"{words[v]} {', '.join(by_verdict[v])}" if v in words else f"{v} than {', '.join(by_verdict[v])}"
            for v in ordered
        )

    best = leaders[0] if len(leaders) == 1 else None
    lead_text = (
        f"Δ{metric.removeprefix('eval/')} {lead.text()} against the next cell"
        if lead
        else "unpaired with the next cell"
    )
    if best and lead is not None and lead.verdict(mode) == "better":
        out = [f"best cell {best} ({lead_text}): {standing(best, False)}"]
    elif best:
        out = [f"no cell is resolvably best by {metric}: the leader {best} ({lead_text}): {standing(best, False)}"]
    else:
        out = [f"no best cell: {', '.join(leaders)} tie at {metric} {number_text(stats[leaders[0]].mean)}"]  # type: ignore[union-attr]
    if pairing:
        classes: dict[str, list[str]] = {}
        for name in cells:
            if name != best and stats[name] is not None:
                classes.setdefault(standing(name, True), []).append(name)
        out += [f"{'cell' if len(names) == 1 else 'cells'} {', '.join(names)}: "
                f"{standing(names[0], len(names) > 1)}" for names in classes.values()]
        by_verdict: dict[str, list[str]] = {}
        for name, verdict in pairing.verdicts.items():
            by_verdict.setdefault(verdict, []).append(name)
        if by_verdict:
            out.append(
                f"against {pairing.reference}: " + "; ".join(f"{', '.join(n)} {v}" for v, n in by_verdict.items())
            )
    failed = [name for name in cells if stats[name] is None]
    if failed:
        out.append(f"no result (failed or not run): {', '.join(failed)}")
    return out


def _paired_record(pairing: _Pairing, name: str, shown: list[str], metric: str) -> dict[str, object]:
    record: dict[str, object] = {}
    for m in shown:
        d = pairing.delta(name, m, metric)
        ok = isinstance(d, PairedDifference)
        record.update({f"{m} delta": d.mean if ok else None, f"{m} delta low": d.low if ok else None,
                       f"{m} delta high": d.high if ok else None})
    settle = pairing.settled.get(name)
    paired = isinstance(pairing.diffs.get((name, metric)), PairedDifference)
    record[f"{metric} delta covers"] = settle.decision.interval.covers if settle else "objects" if paired else ""
    record["verdict"] = pairing.verdicts.get(name, "")
    record["beats baselines"] = ";".join(pairing.beats(name))
    return record
