"""Every cell and baseline of a results table paired with the reference cell on the same objects.

For each shown metric (the table's metric and its partner), a cell's per-object scores, seeds averaged
per object, are compared with the reference cell's and with each trivial baseline's on that cell's own
objects (:mod:`sweeps.compare.bootstrap`: mean difference, 95% bootstrap interval, verdict); a verdict
weighs the metric and its partner (:func:`sweeps.compare.rules.weighed`). A cell that ran until its
comparison settled (:mod:`sweeps.compare.sequential`) keeps its interval over seeds and objects and its
verdict. :mod:`sweeps.compare.table` lays the results out as columns.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from sweeps.compare.bootstrap import PairedDifference, UnpairedError, compare, per_object_means
from sweeps.compare.outcomes import TrialOutcome, finished
from sweeps.compare.rules import object_column, partner_mode, weighed
from sweeps.compare.sequential import SettleRecord

__all__ = ["Pairing", "lead_difference", "paired_record"]


def _object_scores(group: Sequence[TrialOutcome], key: str, category: str | None) -> dict[str, float]:
    """``object_id →`` score under ``key`` of a cell's finished trials, seeds averaged per object."""
    trials = [
        [r for r in o.objects if category is None or r["category"] == category] for o in finished(group) if o.objects
    ]
    return per_object_means(trials, key) if trials and all(key in r for t in trials for r in t) else {}


@dataclass
class Pairing:
    """Paired differences of every cell and baseline against the reference cell, per shown metric."""

    reference: str
    diffs: dict[tuple[str, str], PairedDifference | str]
    """``(row name, metric) →`` the difference, or why there is none."""
    against: dict[str, dict[str, str]]
    """Cell → baseline → weighed verdict of the cell against it (``better``: on the metric, not worse on the
    partner)."""
    verdicts: dict[str, str]
    """Cell → its weighed verdict against the reference cell; a settled cell's says after how many seeds."""
    settled: Mapping[str, SettleRecord]
    notes: list[str]

    @classmethod
    def build(cls, cells: dict[str, list[TrialOutcome]], reference: str, shown: list[str],
              mode: Literal["min", "max"], baselines: list[str], settled: Mapping[str, SettleRecord]) -> Pairing:
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
        """Row ``name``'s Δ on ``m``: a settled cell's interval over seeds and objects on the metric, else the
        paired one."""
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


def lead_difference(
    cells: dict[str, list[TrialOutcome]], best: str, runner_up: str, metric: str
) -> PairedDifference | None:
    """The leader ``best`` against the next cell ``runner_up`` on ``metric``, paired per object; None if unpaired."""
    ours, theirs = (_object_scores(cells[n], *object_column(metric)) for n in (best, runner_up))  # type: ignore[misc]
    return compare(ours, theirs, (best, runner_up)) if ours and theirs and set(ours) == set(theirs) else None


def paired_record(pairing: Pairing, name: str, shown: list[str], metric: str) -> dict[str, object]:
    """Cell ``name``'s Δ per shown metric (mean and interval), what its interval covers, its verdict and the
    baselines it beats, as numbers for the CSV."""
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
