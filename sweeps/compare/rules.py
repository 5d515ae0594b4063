"""The rules a results table reads numbers by (each metric's partner, direction and precision are in its
record, :mod:`cdm.metric_names`): which metrics a reader shows, how baselines are named, how verdicts on two
metrics combine into one, and the notes that say what produced the numbers. Plain functions of names, numbers
and the spec."""

from __future__ import annotations

import math
import statistics
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from cdm.config import load_config
from cdm.metric_names import number_text, partner
from sweeps.plan.spec import Spec

__all__ = ["PROTOCOL_NOTE", "TOO_FEW", "Stat", "baseline_key", "baseline_name", "headline", "lambda_source",
           "machine_note", "settings_note", "settings_notes", "weighed"]


def headline(metric: str) -> list[str]:
    """What every reader shows of a sweep: ``metric`` and its partner (:func:`cdm.metric_names.partner`), if any."""
    return [m for m in (metric, partner(metric)) if m is not None]


def baseline_key(baseline: str, metric: str) -> str:
    """Where baseline ``baseline``'s score on ``metric`` (``eval/f1/chair`` or ``f1``) is logged and kept in
    ``objects.csv``: ``baseline/<baseline>/f1/chair``."""
    return f"baseline/{baseline}/{metric.removeprefix('eval/')}"


def baseline_name(baseline: str) -> str:
    """A baseline as a sentence or a plot names it: ``Gaussian``, ``category mean``."""
    return {"gaussian": "Gaussian"}.get(baseline, baseline.replace("_", " "))


@dataclass(frozen=True)
class Stat:
    """Mean ± standard deviation over a cell's seeds (no ± from one seed), as the table prints it."""

    mean: float
    std: float | None
    n: int

    @classmethod
    def of(cls, values: Sequence[float]) -> Stat | None:
        values = [v for v in values if math.isfinite(v)]
        if not values:
            return None
        return cls(statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None, len(values))

    def text(self) -> str:
        return number_text(self.mean) + ("" if self.std is None else f" ± {number_text(self.std, self.mean)}")


def weighed(verdicts: Sequence[tuple[str, str]]) -> str:
    """One verdict from ``(metric, verdict)`` pairs, the sweep's metric first, then its partner.

    The metric's verdict when every other one agrees with it or is unclear; otherwise each clear one
    by name (``better on f1, worse on cd``; ``worse on cd`` when the metric alone is unclear), so a
    difference the partner's interval shows is never read as "no clear difference".
    """
    (metric, first), *rest = verdicts
    others = [(m, v) for m, v in rest if v not in ("no clear difference", first)]
    if not others:
        return first
    named = ([] if first == "no clear difference" else [(metric, first)]) + others
    return ", ".join(f"{v} on {m.removeprefix('eval/')}" for m, v in named)


def settings_note(
    profile: str, steps: object, targets: Iterable[str], lambdas: Iterable[float], lambda_from: str,
    compute_s: object = None,
) -> str:
    """The table's first note: what produced the numbers (profile, budget, prediction target, λ).

    ``lambda_from`` says where the λ of Eq. 6 (``priors.lambda_3d``) was set (``profile local``,
    ``--set``, ``the spec``, ``the config default``): the paper gives no value, so the paper's column
    was not measured with it. ``compute_s``: a budget in seconds of compute, said with its unit before the steps.
    """
    def per_cell(values: list[str]) -> str:
        return values[0] if len(values) == 1 else "per cell (" + ", ".join(values) + ")"

    shown, values = per_cell(sorted(set(targets))), sorted(set(lambdas))
    lam = per_cell([f"{v:g}" for v in values]) if values else "searched"
    budget = f"{steps} steps" if compute_s is None else f"{float(compute_s):g} s of compute (at most {steps} steps)"
    return (f"profile {profile}: {budget} per trial; prediction target {shown}; "
            f"λ (priors.lambda_3d, Eq. 6) {lam}, from {lambda_from}, not from the paper")


PROTOCOL_NOTE = "protocol: "
"""How a note of the table that is a line of the protocol card begins."""


def lambda_source(spec: Spec, profile: str, fixed: dict[str, Any], sets: dict[str, Any]) -> str:
    """Where a sweep's λ (``priors.lambda_3d``) comes from, for :func:`settings_note`: the spec's search or cells,
    ``--set``, the spec's base, the profile, or the config default (the levels of :mod:`sweeps.plan.trials`)."""
    key = "priors.lambda_3d"
    if key in spec.search.space:
        return "the spec's search"
    if key in spec.grid or any(key in c.set for c in spec.cells):
        return "the spec's cells"
    if key in sets:
        return "--set"
    if key in spec.base:
        return "the spec's base"
    if key in fixed:
        return f"profile {profile}"
    return "the config default"


def _machine(tags: Mapping[str, str]) -> str:
    """One trial's machine from its ``repro.*`` tags (:func:`cdm.provenance.machine_record`), on one line."""
    def get(key: str) -> str:
        return " ".join(tags.get(f"repro.{key}", "?").split())  # a recorded newline must not break the list

    return (f"{get('cpu_model')} ({get('cpu_isa')}), ATen {get('cpu_capability')}, {get('math_libraries')}, "
            f"kernel pins {get('kernel_pins')}, packages {get('packages_digest')}")


def machine_note(trials: Iterable[Mapping[str, str]]) -> str:
    """The table's note on the machine its trials ran on, from each trial's ``repro.*`` tags: on CPU, MKL and
    oneDNN pick their kernels per CPU, so another CPU type moves the numbers (docs/local-results.md)."""
    seen = Counter(_machine(tags) for tags in trials if "repro.cpu_model" in tags)
    where = " (every package: each child run's environment/packages.txt)"
    if not seen:
        return "machine: not recorded (trials from before the record named it)"
    if len(seen) == 1:
        return f"machine: {next(iter(seen))}{where}"
    return ("machines differ between trials, and so may their numbers: "
            + "; ".join(f"{n} on {machine}" for machine, n in seen.most_common()) + where)


def settings_notes(spec: Spec, profile: str, steps: object, fixed: dict[str, Any], sets: dict[str, Any],
                   card: Iterable[str], trials: Iterable[tuple[str, float]] = (),
                   machines: Iterable[Mapping[str, str]] | None = None, compute_s: object = None) -> list[str]:
    """The table's notes on what produced the numbers, the runner's and the report's alike (the one home of
    that rule): the :func:`settings_note` (a λ the spec searches is "searched", whatever the trials drew),
    then the protocol card (:mod:`sweeps.plan.protocol`) a line per note.

    ``fixed``/``sets``: the plan's fixed overrides and ``--set`` values, where :func:`lambda_source` looks for
    λ. ``trials``: each trial's resolved (``diffusion.prediction``, ``priors.lambda_3d``); none (a sampled
    search before its trials, a sweep whose trials recorded none) stands for ``fixed`` and ``sets`` resolved
    by :func:`cdm.config.load_config`, as every trial's config is. ``machines``: each trial's tags, for the
    :func:`machine_note` after the first note. ``compute_s``: the profile's budget in seconds of compute, if any.
    """
    trials = list(trials)
    if not trials:
        cfg = load_config(None, {**fixed, **sets})
        trials = [(cfg.diffusion.prediction, cfg.priors.lambda_3d)]
    targets, lambdas = [t for t, _ in trials], [lam for _, lam in trials]
    searched = "priors.lambda_3d" in spec.search.space
    return [
        settings_note(profile, steps, targets, () if searched else lambdas, lambda_source(spec, profile, fixed, sets),
                      compute_s),
        *([] if machines is None else [machine_note(machines)]),
        *(PROTOCOL_NOTE + line for line in card),
    ]


TOO_FEW = "too few objects to tell"
"""What a verdict adds when its interval was wider than the metric allows and was clipped (``delta_range``)."""
