"""Every cell and baseline of a results table paired with the reference cell on the same objects, per shown
metric (:mod:`sweeps.compare.bootstrap`; seeds averaged per object): Δ, a verdict weighing the metric and its
partner (:func:`sweeps.compare.rules.weighed`), the baselines each cell beats on its own objects. A cell that ran
until its comparison settled (:mod:`sweeps.compare.sequential`) keeps its interval over seeds and objects.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from cdm.metric_names import delta_range, object_column
from cdm.metric_names import mode as metric_mode
from sweeps.compare.bootstrap import PairedDifference, UnpairedError, compare, per_object_means
from sweeps.compare.outcomes import TrialOutcome, finished
from sweeps.compare.rules import TOO_FEW, baseline_key, weighed
from sweeps.compare.sequential import Decision, SettleRecord, decide
from sweeps.plan.trials import split_label

__all__ = ["Lead", "Pairing", "lead_difference", "paired_record", "seeds_vary"]


def _object_scores(group: Sequence[TrialOutcome], key: str, category: str | None) -> dict[str, float]:
    """``object_id →`` score under ``key`` of a cell's finished trials, seeds averaged per object."""
    trials = [
        [r for r in o.objects if category is None or r["category"] == category] for o in finished(group) if o.objects
    ]
    return per_object_means(trials, key) if trials and all(key in r for t in trials for r in t) else {}


def _seed_scores(group: Sequence[TrialOutcome], key: str, category: str | None) -> dict[int, dict[str, float]]:
    """Training seed → ``object_id →`` score under ``key`` of a cell's finished trials (what
    :func:`sweeps.compare.sequential.decide` pairs), per seed as :func:`_object_scores` per cell."""
    out = {}
    for o in finished(group):
        scores = _object_scores([o], key, category)
        seed = split_label(o.label)[1]
        if scores and seed is not None:
            out[int(seed)] = scores
    return out


def seeds_vary(cells: Mapping[str, Sequence[TrialOutcome]]) -> bool:
    """Some cell has more than one finished trial with per-object scores: its seeds' spread is to be counted."""
    return any(sum(bool(o.objects) for o in finished(group)) > 1 for group in cells.values())


def _over_seeds(cell: Sequence[TrialOutcome], reference: Sequence[TrialOutcome], metric: str,
                mode: Literal["min", "max"], looks: int) -> Decision | None:
    """``cell`` against ``reference`` on ``metric`` over the seeds both ran and the objects both scored, as a
    sequential sweep's rows decide (:func:`sweeps.compare.sequential.decide`, its interval spending
    (1 − level) / ``looks``); None where they pair on no seed or object."""
    column, category = object_column(metric)  # type: ignore[misc]
    try:
        return decide(_seed_scores(cell, column, category), _seed_scores(reference, column, category), mode=mode,
                      margin=None, look=looks, looks=looks)
    except (UnpairedError, ValueError):  # no seed in common, other objects, or one object
        return None


def _as_difference(decision: Decision, metric: str) -> PairedDifference:
    i = decision.interval
    return PairedDifference(i.mean, i.low, i.high, i.objects).within(delta_range(metric))


def _plain(verdict: str) -> str:
    """A verdict over seeds as a row without a seeds rule says it: ``open`` is no clear difference."""
    return "no clear difference" if verdict == "open" else verdict


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
    seeded: dict[str, Decision]
    """Cell → its decision over seeds and objects on the metric, where seeds vary in a sweep of fixed seeds
    (a sequential sweep's cells have theirs in ``settled``)."""

    @classmethod
    def build(cls, cells: dict[str, list[TrialOutcome]], reference: str, shown: list[str],
              mode: Literal["min", "max"], baselines: list[str], settled: Mapping[str, SettleRecord]) -> Pairing:
        pairing = cls(reference, {}, {}, {}, {n: r for n, r in settled.items() if n in cells and n != reference}, [],
                      {})
        metric, modes = shown[0], {m: mode if m == shown[0] else metric_mode(m) for m in shown}
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
                    ours, theirs = scores[name], _object_scores(group, baseline_key(b, column), category)
                    if ours and set(ours) == set(theirs):
                        to_baseline[(name, b, m)] = compare(ours, theirs, (name, b)).verdict(modes[m])
        for (name, b, m), verdict in to_baseline.items():
            if m == metric:
                others = [(p, to_baseline[(name, b, p)]) for p in shown[1:] if (name, b, p) in to_baseline]
                pairing.against.setdefault(name, {})[b] = weighed([(m, verdict), *others])
        if seeds_vary(cells):  # the metric's verdict over seeds and objects, as a sequential sweep's
            for name in cells:
                if name != reference and name not in pairing.settled and (name, metric) in pairing.diffs:
                    decision = _over_seeds(cells[name], cells[reference], metric, mode, 1)
                    if decision is not None and decision.interval.seeds > 1:  # else paired per object, as before
                        pairing.seeded[name] = decision
        for name in cells:
            found = {m: d.verdict(modes[m]) for m in shown
                     if isinstance(d := pairing.delta(name, m, metric), PairedDifference)}
            if name in pairing.seeded:
                found[metric] = _plain(pairing.seeded[name].verdict)
            # An interval cut to the metric's range that still holds 0 tells nothing: said so, not "unclear".
            found |= {m: TOO_FEW for m, v in found.items()
                      if v == "no clear difference" and pairing.delta(name, m, metric).clipped}  # type: ignore[union-attr]
            record = pairing.settled.get(name)
            if record is not None:
                # The partner was not decided on: its interval over objects only, said as such.
                aside = [f" ({v} on {m.removeprefix('eval/')}, objects only)" for m, v in found.items()
                           if m != metric and v not in ("no clear difference", record.decision.verdict)]
                # Its seeds column says how many.
                head = TOO_FEW if found.get(metric) == TOO_FEW and not record.decision.settled else record.text()
                pairing.verdicts[name] = "".join([head, *aside])
            elif metric in found:
                pairing.verdicts[name] = weighed(
                    [(metric, found[metric])] + [(m, v) for m, v in found.items() if m != metric]
                )
        if unpaired:
            pairing.notes.append(f"not paired with {reference}, evaluated on other objects or settings (a paired "
                                 f"comparison needs the same evaluation set): {', '.join(unpaired)}")
        return pairing

    def clipped(self, shown: list[str], metric: str) -> list[str]:
        """The shown metrics some row's Δ interval was cut on (:func:`cdm.metric_names.delta_range`)."""
        return [m for m in shown if any(getattr(self.delta(n, m, metric), "clipped", False) for n, _ in self.diffs)]

    def beats(self, name: str) -> list[str]:
        return [b for b, v in self.against.get(name, {}).items() if v == "better"]

    def decision(self, name: str) -> Decision | None:
        """Row ``name``'s decision over seeds and objects on the metric: a settled cell's, else its own where seeds
        vary in a sweep of fixed seeds."""
        return self.settled[name].decision if name in self.settled else self.seeded.get(name)

    def delta(self, name: str, m: str, metric: str) -> PairedDifference | str | None:
        """Row ``name``'s Δ on ``m``: on the metric, over seeds and objects where it has a :meth:`decision`, else
        the paired one; cut to the values the Δ can take (:func:`cdm.metric_names.delta_range`)."""
        decision = self.decision(name)
        if decision is not None and m == metric:
            return _as_difference(decision, m)
        d = self.diffs.get((name, m))
        return d.within(delta_range(m)) if isinstance(d, PairedDifference) else d

    def columns(self, name: str, shown: list[str], metric: str) -> list[str]:
        """A cell's Δ per shown metric, verdict and the baselines it beats."""
        out = []
        for m in shown:
            d = self.delta(name, m, metric)
            out.append(
                "reference" if name == self.reference else d.text() if isinstance(d, PairedDifference) else d or "–"
            )
        return out + [self.verdicts.get(name, ""), ", ".join(self.beats(name)) or "none"]


@dataclass(frozen=True)
class Lead:
    """The leader against the next cell: the difference, its verdict and what its interval covers."""

    diff: PairedDifference
    verdict: str
    """``better``/``worse``/``no clear difference``, or ``open`` where one seed of each settles nothing."""
    covers: str
    """``objects``, or ``seeds and objects``."""


def lead_difference(cells: dict[str, list[TrialOutcome]], best: str, runner_up: str, metric: str,
                    mode: Literal["min", "max"] = "max", looks: int | None = None) -> Lead | None:
    """The leader ``best`` against the next cell ``runner_up`` on ``metric``; None if unpaired. Where seeds vary,
    over seeds and objects as the rows' verdicts: a sequential sweep's (``looks``: its planned looks; its
    interval spends (1 − level) / looks, and one seed in common settles nothing), else a sweep of fixed seeds'
    (one look; paired per object where the two share one seed). Else paired per object."""
    if seeds_vary(cells):
        decision = _over_seeds(cells[best], cells[runner_up], metric, mode, looks or 1)
        if decision is not None and (looks is not None or decision.interval.seeds > 1):
            return Lead(_as_difference(decision, metric), decision.verdict, decision.interval.covers)
    ours, theirs = (_object_scores(cells[n], *object_column(metric)) for n in (best, runner_up))  # type: ignore[misc]
    if not (ours and theirs and set(ours) == set(theirs)):
        return None
    diff = compare(ours, theirs, (best, runner_up)).within(delta_range(metric))
    return Lead(diff, diff.verdict(mode), "objects")


def paired_record(pairing: Pairing, name: str, shown: list[str], metric: str) -> dict[str, object]:
    """Cell ``name``'s Δ per shown metric (mean and interval), what its interval covers, its verdict and the
    baselines it beats, as numbers for the CSV."""
    record: dict[str, object] = {}
    for m in shown:
        d = pairing.delta(name, m, metric)
        ok = isinstance(d, PairedDifference)
        record.update({f"{m} delta": d.mean if ok else None, f"{m} delta low": d.low if ok else None,
                       f"{m} delta high": d.high if ok else None})
    decision = pairing.decision(name)
    paired = isinstance(pairing.diffs.get((name, metric)), PairedDifference)
    record[f"{metric} delta covers"] = decision.interval.covers if decision else "objects" if paired else ""
    record["verdict"] = pairing.verdicts.get(name, "")
    record["beats baselines"] = ";".join(pairing.beats(name))
    return record
