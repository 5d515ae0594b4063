"""The results table of a sweep: one row per cell, mean ± std over seeds, the paper's number beside it.

Knows nothing of Ray or MLflow: the runner turns finished trials into
:class:`sweeps.compare.outcomes.TrialOutcome` s and this module aggregates and formats them — plain text
for the terminal, Markdown and CSV for the sweep folder. Trivial baselines the trainer reports
(``baseline/<name>/<metric>``: sphere, Gaussian, category mean, retrieval) get their own rows, so a local
result is never read without them (benchmarks/RESULTS.md, "Which recipe learns"). Where trials carry their
per-object scores, the Δ columns pair every row with a reference cell (:mod:`sweeps.compare.pairing`).
"""

from __future__ import annotations

import csv
import io
import textwrap
import unicodedata
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from cdm.baseline_names import BASELINES
from cdm.metric_names import COMPUTE_METRIC, COMPUTE_UNIT, F1, delta_range, f1_unit, number_text, object_column
from cdm.metric_names import mode as metric_mode
from sweeps.compare.bootstrap import PairedDifference
from sweeps.compare.outcomes import TrialOutcome, finished
from sweeps.compare.pairing import Lead, Pairing, lead_difference, paired_record, seeds_vary
from sweeps.compare.rules import TOO_FEW, Stat, baseline_key, baseline_name, headline
from sweeps.compare.sequential import FOOTNOTE as SETTLED_FOOTNOTE
from sweeps.compare.sequential import SettleRecord
from sweeps.plan.describe import wrapped
from sweeps.store.files import write_file

__all__ = ["COST_COLUMN", "NO_RESULT", "ResultsTable", "build_table", "display_width"]


def display_width(text: str) -> int:
    """Terminal columns ``text`` takes: a wide (CJK) character two, a combining mark none, any other one
    (★, Δ, ±, λ: one column, though two or three bytes in UTF-8)."""
    return sum(0 if unicodedata.combining(c) else 2 if unicodedata.east_asian_width(c) in "WF" else 1 for c in text)


COST_COLUMN = "compute s"
"""The results table's cost column: a cell's seconds of compute, the mean over its finished trials of what each
reported (:data:`cdm.metric_names.COMPUTE_METRIC`)."""

NO_RESULT = "no cell finished a trial"
"""The table's headline when no cell has a result."""

_WHOLE = "[95% CI]"
"""A header's words a wrap keeps on one line."""


def _bytes(line: str) -> int:
    return len(line.encode())


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
    f1_thresholds: tuple[float, ...] = ()
    """The trials' ``eval.f1_threshold`` values (distinct, sorted): what every F1 label of the sweep names."""
    reference: str | None = None
    """The cell every row is paired with; None when the table pairs none."""

    @property
    def headline(self) -> str:
        """The table's answer in a sentence: its first summary line."""
        return self.summary[0] if self.summary else NO_RESULT

    def record(self, cell: str) -> dict[str, object]:
        """The CSV record of row ``cell`` (``{}`` when there is none)."""
        return next((r for r in self.records if r["cell"] == cell), {})

    def difference(self, cell: str, metric: str) -> PairedDifference | None:
        """Row ``cell``'s Δ on ``metric`` against :attr:`reference`, as its record holds it (``n`` not kept: 0)."""
        found = self.record(cell)
        if found.get(f"{metric} delta") is None:
            return None
        return PairedDifference(*(float(found[f"{metric} delta{end}"]) for end in ("", " low", " high")), 0)  # type: ignore[arg-type]

    def _filled(self, names: Sequence[str] | None = None) -> list[int]:
        """Indices of the columns named (default: all) that some row fills; the first column always."""
        return [i for i, h in enumerate(self.header)
                if (names is None or h in names) and (i == 0 or any(r[i] for r in self.rows))]

    def text(self, width: int = 120) -> str:
        """The table for a terminal, every line at most ``width`` UTF-8 bytes: an upper bound of its columns in
        any terminal, one where ★, Δ and λ take two columns (East Asian "ambiguous" width) included. The wide
        columns stay in ``results.md`` and empty ones are left out; then, until it fits, headers wider than their
        column's values wrap over several lines (long cell names make the Δ header long; its ``[95% CI]`` stays
        whole) before each ``narrowing`` column is dropped in turn; summary and notes are wrapped as a plan's
        description is (:func:`sweeps.plan.describe.wrapped`: a word longer than ``width`` stays whole)."""
        keep = [i for i in self._filled() if self.header[i] not in self.wide_only]
        for name in (*self.narrowing, None):
            out = self._lines(keep, wrap=False)
            if max(map(_bytes, out)) > width:
                out = self._lines(keep, wrap=True)
            if max(map(_bytes, out)) <= width or name is None:
                break
            keep = [i for i in keep if self.header[i] != name]
        dropped = [h for i, h in enumerate(self.header) if i not in keep and any(r[i] for r in self.rows)]
        categories = [h for h in dropped if h.count("/") == 2]
        if categories:  # eval/f1/chair, eval/f1/lamp, … → eval/f1/<category>
            dropped[dropped.index(categories[0])] = categories[0].rsplit("/", 1)[0] + "/<category>"
            dropped = [h for h in dropped if h not in categories]
        notes = self.notes + ["not shown here, in results.md and results.csv: " + ", ".join(dropped)] * bool(dropped)
        for block in (self.summary, notes):
            out += [""] + [wrapped(line, width) for line in block] if block else []
        return "\n".join(out)

    def _lines(self, keep: list[int], wrap: bool) -> list[str]:
        """The title, header, rule and rows of the columns ``keep``; with ``wrap``, a column is as wide as its
        values (or its header's longest word) and its header wraps to that width."""
        heads = [self.header[i].replace(_WHOLE, _WHOLE.replace(" ", "\u00a0")) for i in keep]
        sizes = [max([display_width(r[i]) for r in self.rows]
                     + ([display_width(w) for w in h.split(" ")] if wrap else [display_width(h)]))
                 for i, h in zip(keep, heads)]
        wrapped = [[w.replace("\u00a0", " ") for w in textwrap.wrap(h, size)] or [""] for h, size in zip(heads, sizes)]
        depth = max(len(lines) for lines in wrapped)
        # A wrapped header sits on the bottom lines, next to the one-line headers.
        header = [[([""] * (depth - len(lines)) + lines)[k] for lines in wrapped] for k in range(depth)]

        def line(cells: Sequence[str]) -> str:
            return "  ".join(c + " " * (w - display_width(c)) for c, w in zip(cells, sizes)).rstrip()

        rows = [line([r[i] for i in keep]) for r in self.rows]
        return [self.title, *map(line, header), "  ".join("-" * w for w in sizes), *rows]

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


@dataclass(frozen=True)
class _Columns:
    """What a table shows, shared by its header, its rows and its notes."""

    metric: str
    mode: Literal["min", "max"]
    shown: list[str]
    """The metric and its partner (:func:`sweeps.compare.rules.headline`), each with the paper's beside."""
    baselines: list[str]
    """Baselines some trial scored, in cdm.evaluate's order, weakest first (sphere … retrieval); any other after."""
    categories: list[str]
    """Categories with a ``<metric>/<category>`` column, in the wide table only."""
    paper_label: bool
    """A ``paper setting`` column: some trial names the paper's row it stands for."""
    pairing: Pairing | None
    cost: bool = False
    """A ``compute s`` column: some trial reported its seconds of compute (:data:`cdm.metric_names.COMPUTE_METRIC`)."""

    @classmethod
    def of(cls, outcomes: Sequence[TrialOutcome], cells: dict[str, list[TrialOutcome]], metric: str,
           mode: Literal["min", "max"], compare_to: str | None, settled: Mapping[str, SettleRecord]) -> _Columns:
        """The columns of ``outcomes``, paired with ``compare_to`` (default: the first cell) where it has objects."""
        shown = headline(metric)
        found = {k.split("/")[1] for o in outcomes for k in o.metrics if k.startswith("baseline/")}
        baselines = [b for b in BASELINES if b in found] + sorted(found - set(BASELINES))
        reference = compare_to or next(iter(cells), None)
        pairing = None
        if object_column(metric) and reference in cells and any(o.objects for o in finished(cells[reference])):
            pairing = Pairing.build(cells, reference, shown, mode, baselines, settled)
        prefix = metric + "/"
        categories = sorted({k[len(prefix):] for o in outcomes for k in o.metrics if k.startswith(prefix)})
        return cls(metric, mode, shown, baselines, categories, any(o.paper_label for o in outcomes), pairing,
                   any(COMPUTE_METRIC in o.metrics for o in outcomes))

    @property
    def partner(self) -> str | None:
        return self.shown[1] if len(self.shown) > 1 else None

    @property
    def seeds(self) -> bool:
        """A ``seeds`` column: some cell ran until its comparison settled."""
        return bool(self.pairing and self.pairing.settled)

    @property
    def per_category(self) -> list[str]:
        return [f"{self.metric}/{c}" for c in self.categories]

    def delta(self, m: str) -> str:
        """The header of the Δ column of ``m``."""
        return f"Δ{m.removeprefix('eval/')} vs {self.pairing.reference} [95% CI]"  # type: ignore[union-attr]

    def header(self) -> list[str]:
        out = ["cell"] + (["paper setting"] if self.paper_label else []) + ["trials"] + ["seeds"] * self.seeds
        out += [COST_COLUMN] * self.cost
        for m in self.shown:
            out += [m, f"paper {m}"]
        out += self.per_category
        return out + ([*map(self.delta, self.shown), "verdict", "beats baselines"] if self.pairing else [])

    def narrowing(self) -> tuple[str, ...]:
        """:attr:`ResultsTable.narrowing`; last, the trial counts: a long verdict (a sequential cell's, with its
        partner aside) still fits."""
        second = self.partner
        return (*([self.delta(second)] if self.pairing and second else []), "paper setting",
                *([f"paper {second}", second] if second else []), COST_COLUMN, "trials")

    def answer(self) -> tuple[str, ...]:
        """:attr:`ResultsTable.answer`."""
        return ("cell", *["seeds"] * self.seeds, *self.shown,
                *([self.delta(self.metric), "verdict"] if self.pairing else []))


@dataclass(frozen=True)
class _Ranking:
    """The cells by their mean metric: each cell's :class:`Stat` and the leaders, the cells that print the best
    mean (a star between them would rest on digits nobody sees)."""

    stats: dict[str, Stat | None]
    order: list[str]
    """The cells with a result, best first."""
    leaders: list[str]

    @classmethod
    def of(cls, cells: dict[str, list[TrialOutcome]], metric: str, mode: Literal["min", "max"]) -> _Ranking:
        stats = {name: Stat.of([o.metrics[metric] for o in finished(group) if metric in o.metrics])
                 for name, group in cells.items()}
        order = [n for _, n in sorted((s.mean if mode == "min" else -s.mean, n) for n, s in stats.items() if s)]
        top = number_text(stats[order[0]].mean) if order else None  # type: ignore[union-attr]
        return cls(stats, order, [n for n in order if number_text(stats[n].mean) == top])  # type: ignore[union-attr]

    @property
    def best(self) -> str | None:
        """The starred cell: the leader, where it leads alone."""
        return self.leaders[0] if len(self.leaders) == 1 else None

    def mark(self, name: str) -> str:
        return " ★" if name == self.best else " (tied)" if self.best is None and name in self.leaders else ""


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

    With per-object rows on the trials, every row is paired with ``compare_to`` (default: the first cell).
    ``settled`` (cell → where its run until settled stopped) adds a ``seeds`` column and puts that record's
    interval over seeds and objects, and its verdict, in the cell's row. ``settings`` lines (what produced the
    numbers) head the notes.
    """
    cells: dict[str, list[TrialOutcome]] = {}
    for o in outcomes:
        cells.setdefault(o.cell, []).append(o)
    columns = _Columns.of(outcomes, cells, metric, mode, compare_to, settled or {})
    ranking = _Ranking.of(cells, metric, mode)
    made = [_cell_row(columns, name, group, ranking) for name, group in cells.items()]
    if metric.startswith("eval/"):
        made += [_baseline_row(columns, b, finished(outcomes)) for b in columns.baselines]
    looks = max((r.looks for r in settled.values()), default=1) if settled else None
    lead = (lead_difference(cells, ranking.best, ranking.order[1], metric, mode, looks)
            if columns.pairing and ranking.best and len(ranking.order) > 1 else None)
    return ResultsTable(
        title, columns.header(), [row for row, _ in made], [record for _, record in made],
        list(settings) + _notes(columns, outcomes, cells, paper_note, ranking), ranking.best,
        _summary(columns, cells, ranking, lead), frozenset(columns.per_category + ["beats baselines"]),
        columns.narrowing(), columns.answer(), tuple(sorted({o.f1_threshold for o in outcomes})),
        columns.pairing.reference if columns.pairing else None,
    )


def _cell_row(
    columns: _Columns, name: str, group: list[TrialOutcome], ranking: _Ranking
) -> tuple[list[str], dict[str, object]]:
    """A cell's row (its trials aggregated over seeds) and its CSV record."""
    first = group[0]
    counts = {s: sum(o.status == s for o in group) for s in ("ok", "stopped", "failed", "pending")}
    trials = f"{counts['ok'] + counts['stopped']}/{len(group)}" + "".join(
        f" ({counts[s]} {s})" for s in ("stopped", "failed", "pending") if counts[s])
    row = [name + ranking.mark(name)] + ([first.paper_label or ""] if columns.paper_label else []) + [trials]
    record: dict[str, object] = {"cell": name, "paper_setting": first.paper_label or "", "best": name == ranking.best,
                                 **counts}
    if columns.seeds:
        settle = columns.pairing.settled.get(name)  # type: ignore[union-attr]
        row.append(f"{settle.seeds} ({settle.reason})" if settle else "")
        record.update({"seeds": settle.seeds if settle else None, "stop reason": settle.reason if settle else ""})
    done = finished(group)
    if columns.cost:  # measured by the trials, not their budget: a trial stopped early cost less
        cost = Stat.of([o.metrics[COMPUTE_METRIC] for o in done if COMPUTE_METRIC in o.metrics])
        row.append("–" if cost is None else f"{cost.mean:.1f}")
        record[f"{COMPUTE_METRIC} mean"] = cost.mean if cost else None
    for m in columns.shown + columns.per_category:
        stat = Stat.of([o.metrics[m] for o in done if m in o.metrics])
        paper = first.paper.get(m)
        text = "failed" if stat is None and counts["failed"] else ("–" if stat is None else stat.text())
        if m in columns.shown:
            row += [text, "" if paper is None else number_text(paper)]
        else:
            row.append(text + ("" if paper is None else f" ({number_text(paper)})"))
        record.update({f"{m} mean": stat.mean if stat else None, f"{m} std": stat.std if stat else None,
                       f"{m} paper": paper})
    if columns.pairing:
        row += columns.pairing.columns(name, columns.shown, columns.metric)
        record.update(paired_record(columns.pairing, name, columns.shown, columns.metric))
    return row, record


def _baseline_row(columns: _Columns, b: str, done: list[TrialOutcome]) -> tuple[list[str], dict[str, object]]:
    """Baseline ``b``'s row and record: it depends on the evaluation data only, not on the cell, so its mean
    over every finished trial is the number."""
    row = [f"baseline: {b}"] + ([""] if columns.paper_label else []) + [""] + [""] * (columns.seeds + columns.cost)
    record: dict[str, object] = {"cell": f"baseline: {b}"}
    for m in columns.shown + columns.per_category:
        stat = Stat.of([o.metrics[baseline_key(b, m)] for o in done if baseline_key(b, m) in o.metrics])
        row += [number_text(stat.mean) if stat else "–"] + ([""] if m in columns.shown else [])
        record.update({f"{m} mean": stat.mean if stat else None})
    if columns.pairing:  # a reference row: no difference to the reference cell, no verdict
        row += [""] * (len(columns.shown) + 2)
    return row, record


def _notes(columns: _Columns, outcomes: Sequence[TrialOutcome], cells: dict[str, list[TrialOutcome]],
           paper_note: str, ranking: _Ranking) -> list[str]:
    """The notes under the table: units, the paper's source, what the star and the Δ columns mean, failures."""
    metric, mode, pairing, second = columns.metric, columns.mode, columns.pairing, columns.partner
    has_f1 = outcomes and any(m.split("/")[1:2] == [F1.name] for m in columns.shown)
    notes = [f1_unit(o.f1_threshold for o in outcomes)] if has_f1 else []
    if paper_note:
        notes.append(f"paper: {paper_note}")
    if columns.cost:
        notes.append(f"{COST_COLUMN}: each cell's measured cost, the mean over its finished trials of the seconds of "
                     f"compute each reported ({COMPUTE_UNIT})")
    if any(c in o.paper for o in outcomes for c in columns.per_category):
        notes.append(f"{metric}/<category> columns: ours (paper) where the paper reports that category")
    seeds = max((len(finished(group)) for group in cells.values()), default=0)
    if ranking.order:
        interval = "interval over seeds and objects (as the verdicts')" if seeds_vary(cells) else "paired interval"
        star = (f"★ highest mean {metric} ({mode}), apart from the next at the printed precision; \"best\" only where "
                f"its {interval} against the next cell excludes 0" if ranking.best else
                f"no ★: {', '.join(ranking.leaders)} tied for best by {metric} ({mode}) at the printed precision")
        notes.append(star + ("; ± is the standard deviation over seeds" if seeds > 1 else ""))
    if pairing:
        weighed = f"{metric} ({mode})" + (f" and {second} ({metric_mode(second)})" if second else "")
        notes.append(f"Δ: mean over the same objects of (row − {pairing.reference}), seeds averaged per object, "
                     f"with a 95% paired bootstrap interval over the objects; verdict and beats baselines by "
                     f"{weighed}, interval excluding 0 (a verdict names each metric when they disagree)")
        notes.append("the bootstrap intervals cover the held-out objects only, not training seeds: "
                     + ("with one seed per cell, another seed can move a cell by more than an interval's width"
                        if seeds == 1 else "the seeds are averaged, their spread is not in the interval"))
        if pairing.seeded:
            notes.append(f"seeds vary: Δ{metric.removeprefix('eval/')} and its verdict (where a cell and "
                         f"{pairing.reference} share two seeds or more) are over training seeds and held-out objects "
                         "instead, Banerjee's two-way t-interval at 95% (sweeps/compare/sequential.py)")
        notes += [SETTLED_FOOTNOTE] if columns.seeds else []
        for m in pairing.clipped(columns.shown, metric):
            low, high = delta_range(m)  # type: ignore[misc]
            notes.append(f"Δ{m.removeprefix('eval/')} intervals reaching past [{low:+g}, {high:+g}] (F1 lies in "
                         f"[0, 1]) are cut to it; where one still holds 0 the verdict says \"{TOO_FEW}\"")
        notes += pairing.notes
    return notes + [f"failed: {o.label} — {o.error or 'no reason recorded'}" for o in outcomes if o.status == "failed"]


def _grouped(pairs: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """``(name, value)`` pairs as value → the names with it, in first-seen order."""
    out: dict[str, list[str]] = {}
    for name, value in pairs:
        out.setdefault(value, []).append(name)
    return out


def _standing(columns: _Columns, ranking: _Ranking, name: str, plural: bool) -> str:
    """How cell ``name`` stands against the baselines (its weighed verdicts), else its mean."""
    against = (columns.pairing.against if columns.pairing else {}).get(name)
    if not against:
        stat = ranking.stats[name]
        return f"{columns.metric} {stat.text()}" if stat else "no result"
    words = {"better": "beat" if plural else "beats", "no clear difference": "level with", "worse": "below"}
    by_verdict = _grouped((baseline_name(b), v) for b, v in against.items())
    ordered = [v for v in words if v in by_verdict] + [v for v in by_verdict if v not in words]
    return "; ".join(f"{words[v]} {', '.join(by_verdict[v])}" if v in words else f"{v} than {', '.join(by_verdict[v])}"
                     for v in ordered)


def _summary(columns: _Columns, cells: dict[str, list[TrialOutcome]], ranking: _Ranking,
             lead: Lead | None) -> list[str]:
    """One sentence per class of cells — the best cell (only when ``lead``, its paired Δ to the next, excludes 0;
    else the leader, said not resolvable), then cells that stand the same against the baselines (weighed
    verdicts), then every cell's verdict against the reference cell — and one for those with no result."""
    if not ranking.leaders:
        return [NO_RESULT] if cells else []
    metric, pairing, best = columns.metric, columns.pairing, ranking.best
    over = ", over seeds and objects" if lead and lead.covers == "seeds and objects" else ""
    lead_text = (f"Δ{metric.removeprefix('eval/')} {lead.diff.text()} against the next cell{over}"
                 + (f", {TOO_FEW}" if lead.diff.clipped else "") if lead else "unpaired with the next cell")
    if best and lead is not None and lead.verdict == "better":
        out = [f"best cell {best} ({lead_text}): {_standing(columns, ranking, best, False)}"]
    elif best:
        out = [f"no cell is resolvably best by {metric}: the leader {best} ({lead_text}): "
               f"{_standing(columns, ranking, best, False)}"]
    else:
        top = number_text(ranking.stats[ranking.leaders[0]].mean)  # type: ignore[union-attr]
        out = [f"no best cell: {', '.join(ranking.leaders)} tie at {metric} {top}"]
    if pairing:
        classes = _grouped((name, _standing(columns, ranking, name, True)) for name in cells
                           if name != best and ranking.stats[name] is not None)
        out += [f"{'cell' if len(names) == 1 else 'cells'} {', '.join(names)}: "
                f"{_standing(columns, ranking, names[0], len(names) > 1)}" for names in classes.values()]
        by_verdict = _grouped(pairing.verdicts.items())
        out += [f"against {pairing.reference}: " + "; ".join(f"{', '.join(n)} {v}" for v, n in by_verdict.items())
                ] if by_verdict else []
    failed = [name for name in cells if ranking.stats[name] is None]
    return out + ([f"no result (failed or not run): {', '.join(failed)}"] if failed else [])
