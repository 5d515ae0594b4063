"""Seeds until a comparison settles: an interval over training seeds and held-out objects, looked at after each round.

A sweep cell and its reference (``compare_to``) are trained at the same seeds and scored on the same
held-out objects. Their per-object differences form an ``S × O`` grid (seeds × objects)

    d[s, o] = cell[s][o] − reference[s][o] = δ + a_s + b_o + e_so

where δ is the recipe's effect, ``a_s`` what training seed ``s`` adds (variance σ_a²), ``b_o`` how the
effect differs between objects (σ_b²) and ``e_so`` the rest (σ_e²). Seeds and objects are both samples
(a crossed two-way random-effects design), so the grand mean splits into two independent errors

    d̄ − δ = X + Y,   X = ā + ē  (Var = E[MS_seed] / (S·O)),   Y = b̄  (Var = σ_b²/O ≤ E[MS_object] / (S·O))

with the two-way mean squares MS_seed = O·var(seed means) (S − 1 degrees of freedom) and
MS_object = S·var(object means) (O − 1), each independent of both errors. The interval is Banerjee's
(Sankhyā A 23, 1961; his conservative answer to the Behrens–Fisher problem, here for two crossed
factors):

    d̄ ± √( t²_{S−1}(1 − α'/2) · MS_seed  +  t²_{O−1}(1 − α'/2) · MS_object ) / √(S·O)

which covers δ with probability ≥ 1 − α' for every ratio of the variances. Satterthwaite's single
t-quantile is the usual alternative; it fails here: when two seeds happen to agree, its degrees of
freedom jump from ≈1 to ≈O exactly when the seed variance is under-estimated.

**Sequential correction: Bonferroni over the planned looks.** The runner looks after every round
(``looks = max − min + 1``), and each look may settle the comparison, so a 1 − α interval at every
look makes a false "better/worse" up to ``looks`` times as likely. Each look spends α' = α / looks
(α = 1 − ``level``): by the union bound the chance that any look's interval misses δ stays ≤ α
whatever the dependence between looks, which Pocock's or O'Brien–Fleming's boundaries (derived for
normal statistics with a known variance) do not promise at one degree of freedom.

**One seed settles nothing.** With one seed the only interval is today's bootstrap over objects
(:func:`sweeps.compare.bootstrap.paired_bootstrap`, at ``level``), labelled ``covers="objects"``; it leaves out
σ_a, so it is shown but its verdict stays ``open``.

**Two seeds settle only large effects.** At S = 2 the seed term's quantile is t₁(1 − α'/2), 51 for four
looks, and MS_seed has one degree of freedom: where seeds dominate the variance, an effect settles at
the first look in 99 % of sweeps only at ~150 first-look standard errors. That is the price of not
knowing the seed variance from two seeds; a spec that expects moderate effects should start at three.

Why these, by simulation (``tests/test_sequential.py``: 2,000 null sweeps per case, 40 objects, 2 to 5
seeds, four looks). False better/worse rate on null cells, seeds dominating (seed sd 0.5, object
sd 0.1, residual 1) / objects dominating (0.05, 1.0, 1):

    this interval, Bonferroni          2.5 %   0.4 %
    the same, no correction           10.1 %   3.1 %
    Satterthwaite, Bonferroni          8.8 %   1.6 %
    t over per-seed means, Bonferroni  3.8 %  11.7 %   (misses σ_b)
    one seed, objects only            55.6 %   7.8 %   (misses σ_a)

Through :func:`decide` in the searcher's loop the null rates are 2.9 % / 0.6 %, and effects of five
first-look standard errors settle in 99 % of sweeps after 3.6 / 3.4 seeds on average.

Knows nothing of Ray or MLflow: the Tune searcher hands in per-object scores per seed.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import stats

from sweeps.compare.bootstrap import PairedDifference, UnpairedError, interval_text, paired_bootstrap

__all__ = ["FOOTNOTE", "Decision", "Scores", "SeedInterval", "SettleRecord", "decide", "two_way_interval"]

Scores = Mapping[int, Mapping[str, float]]
"""Training seed → ``object_id`` → per-object score of that seed's trial (metric units)."""

Verdict = Literal["better", "worse", "level", "open"]

FOOTNOTE = ("seeds column: cells run until their comparison settled; their Δ on the sweep's metric and its "
            "verdict are over training seeds and held-out objects: Banerjee's two-way (seeds × objects) t-interval, "
            "its 5% split evenly over the planned looks (Bonferroni); one seed settles nothing")
"""The results table's footnote for cells that ran until settled: which interval, which correction
(at :func:`decide`'s default ``level``, the one the runner uses)."""


@dataclass(frozen=True)
class SeedInterval:
    """Mean of cell − reference over the paired seeds and objects, with its interval ``[low, high]`` (metric units)."""

    mean: float
    low: float
    high: float
    seeds: int
    """Seeds paired (trained for both the cell and the reference)."""
    objects: int
    """Objects paired (scored by every paired seed of both)."""
    covers: Literal["objects", "seeds and objects"]
    """The variance the interval accounts for: one seed covers the held-out objects only."""

    def text(self) -> str:
        return interval_text(self.mean, self.low, self.high)


@dataclass(frozen=True)
class Decision:
    """What one look concludes about a cell against its reference."""

    interval: SeedInterval
    verdict: Verdict
    """``level``: the interval lies inside ±margin (checked first: the margin says smaller differences do
    not matter, even when they are sure); ``better``/``worse``: it excludes 0 on that side for the
    metric's mode; ``open``: neither, or one seed only."""

    @property
    def settled(self) -> bool:
        return self.verdict != "open"


@dataclass(frozen=True)
class SettleRecord:
    """Where a cell stopped: the seeds it ran, the last look's decision and why it stopped."""

    seeds: int
    decision: Decision
    reason: Literal["settled", "max", "budget"]
    looks: int = 1
    """The sweep's planned looks: its interval spent (1 − level) / ``looks``, as every other one of the sweep's."""

    def text(self) -> str:
        """``better, settled after 2 seeds`` or ``open at 5 seeds``."""
        unit = "seed" if self.seeds == 1 else "seeds"
        if self.decision.settled:
            return f"{self.decision.verdict}, settled after {self.seeds} {unit}"
        return f"open at {self.seeds} {unit}"


def two_way_interval(d: np.ndarray, alpha: float) -> tuple[float, float, float]:
    """Grand mean of ``d`` (S, O: seeds × objects, S ≥ 2, O ≥ 2) and its two-sided 1 − ``alpha`` interval.

    Crossed random seeds and objects, Banerjee's conservative combination of their two t-quantiles
    (module docstring). Returns ``(mean, low, high)`` in the units of ``d``.
    """
    s, o = d.shape
    mean = float(d.mean())
    ms_seed = o * float(d.mean(axis=1).var(ddof=1))
    ms_object = s * float(d.mean(axis=0).var(ddof=1))
    t_seed, t_object = stats.t.ppf(1.0 - alpha / 2.0, [s - 1, o - 1])
    half = float(np.sqrt((t_seed**2 * ms_seed + t_object**2 * ms_object) / (s * o)))
    return mean, mean - half, mean + half


def _grid(cell: Scores, reference: Scores) -> np.ndarray:
    """Differences ``cell − reference`` as (S, O): shared seeds ascending, objects by id."""
    seeds = sorted(set(cell) & set(reference))
    if not seeds:
        raise UnpairedError(f"no training seed in common (cell {sorted(cell)}, reference {sorted(reference)})")
    ids = sorted(reference[seeds[0]])
    for s in seeds:
        for name, scores in (("cell", cell[s]), ("reference", reference[s])):
            if set(scores) != set(ids):
                only = sorted(set(scores) ^ set(ids))
                raise UnpairedError(f"seed {s} of the {name} was evaluated on other objects ({len(only)} not shared, "
                                    f"e.g. {only[0]}); a paired comparison needs the same evaluation set")
    return np.array([[cell[s][i] - reference[s][i] for i in ids] for s in seeds], dtype=float)


def decide(cell: Scores, reference: Scores, *, mode: Literal["min", "max"], margin: float | None,
           look: int, looks: int, level: float = 0.95) -> Decision:
    """The verdict of look ``look`` (1-based) of ``looks`` planned on ``cell`` against ``reference``.

    Seed ``s`` of the cell pairs with seed ``s`` of the reference (seeds only one of them ran are left
    out), objects by id. ``mode`` is the metric's direction (``min``: lower is better); ``margin`` (metric
    units, or None for none) the equivalence margin of a ``level`` verdict; ``level`` the coverage the
    whole sequence of looks keeps: every look's interval spends the same (1 − level)/looks, so ``look``
    is only checked against ``looks``.

    Raises:
        UnpairedError: no seed in common, or a seed scored on other objects than the reference's.
        ValueError: ``look`` outside 1…``looks``, ``level`` outside (0, 1), a negative ``margin``, one object.
    """
    if not 1 <= look <= looks:
        raise ValueError(f"decide: look must be in 1…looks (got look={look}, looks={looks})")
    if not 0.0 < level < 1.0:
        raise ValueError(f"decide: level must be in (0, 1) (got {level})")
    if margin is not None and margin < 0.0:
        raise ValueError(f"decide: margin is a distance in metric units, ≥ 0 (got {margin})")
    d = _grid(cell, reference)
    s, o = d.shape
    if o < 2:
        raise ValueError(f"decide: a paired interval needs at least 2 objects (got {o})")
    if s == 1:
        one = paired_bootstrap(d[0], np.zeros(o), level=level)
        return Decision(SeedInterval(one.mean, one.low, one.high, 1, o, "objects"), "open")
    mean, low, high = two_way_interval(d, (1.0 - level) / looks)
    interval = SeedInterval(mean, low, high, s, o, "seeds and objects")
    if margin is not None and -margin < low and high < margin:
        return Decision(interval, "level")
    side = PairedDifference(mean, low, high, o).verdict(mode)
    return Decision(interval, "open" if side == "no clear difference" else side)
