"""Seeds until settled: the interval against a hand computation, verdicts, and the error rates by simulation.

The simulation draws per-object, per-seed scores of a cell and its reference with a known effect,
then runs the sequential loop the Tune searcher runs (min 2, max 5 seeds: decide after each round,
an open cell gets one more seed) through :func:`sweeps.compare.sequential.decide` itself. The rejected
intervals are computed beside it, vectorised over sweeps, to show why they were rejected.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import pytest
from scipy import stats

from sweeps.compare.bootstrap import UnpairedError, paired_bootstrap
from sweeps.compare.sequential import FOOTNOTE, Decision, SeedInterval, SettleRecord, decide

MIN_SEEDS, MAX_SEEDS, OBJECTS = 2, 5, 40
LOOKS = MAX_SEEDS - MIN_SEEDS + 1
NULL_SWEEPS, EFFECT_SWEEPS = 2000, 300


class Case(NamedTuple):
    """Standard deviations (metric units) of one simulated ablation; residual per-object noise is 1."""

    seed: float
    """Of one trained model's offset over all objects (a cell's and its reference's, independent)."""
    objects: float
    """Of the effect between objects (the cell helps some objects more than others)."""

    def first_look_se(self) -> float:
        """Standard error of the mean difference at the first look (module docstring's Var, S = 2)."""
        s, o = MIN_SEEDS, OBJECTS
        return float(np.sqrt(2 * self.seed**2 / s + self.objects**2 / o + 2.0 / (s * o)))


CASES = {"seeds dominate": Case(seed=0.5, objects=0.1), "objects dominate": Case(seed=0.05, objects=1.0)}


def _draw(case: Case, effect: float, sweeps: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cell and reference scores, each (sweeps, MAX_SEEDS, OBJECTS); objects differ in difficulty (sd 3)."""
    difficulty = rng.normal(0.0, 3.0, (sweeps, 1, OBJECTS))

    def model(offset: np.ndarray) -> np.ndarray:
        return difficulty + offset + rng.normal(0.0, case.seed, (sweeps, MAX_SEEDS, 1)) + rng.normal(
            0.0, 1.0, (sweeps, MAX_SEEDS, OBJECTS))

    return model(effect + rng.normal(0.0, case.objects, (sweeps, 1, OBJECTS))), model(np.zeros(1))


def _scores(grid: np.ndarray, seeds: int) -> dict[int, dict[str, float]]:
    """The first ``seeds`` rows of one sweep's (MAX_SEEDS, OBJECTS) grid as the searcher's ``Scores``."""
    return {s: {f"obj{o:02d}": float(grid[s, o]) for o in range(OBJECTS)} for s in range(seeds)}


def _sequential(cell: np.ndarray, reference: np.ndarray, mode: str = "min") -> SettleRecord:
    """One cell run as the searcher runs it: decide after each round; open → one more seed, until max."""
    for look in range(1, LOOKS + 1):
        seeds = MIN_SEEDS + look - 1
        decision = decide(_scores(cell, seeds), _scores(reference, seeds), mode=mode, margin=None,
                          look=look, looks=LOOKS)
        if decision.settled:
            return SettleRecord(seeds, decision, "settled")
    return SettleRecord(MAX_SEEDS, decision, "max")


def _run(case: Case, effect: float, sweeps: int, seed: int) -> list[SettleRecord]:
    cells, references = _draw(case, effect, sweeps, np.random.default_rng(seed))
    return [_sequential(c, r) for c, r in zip(cells, references)]


@pytest.mark.parametrize("name", CASES)
def test_null_cells_are_falsely_settled_at_most_five_percent_of_sweeps(name):
    records = _run(CASES[name], 0.0, NULL_SWEEPS, seed=1)
    false = sum(r.decision.verdict in ("better", "worse") for r in records) / len(records)
    print(f"\n{name}: false better/worse on null cells {false:.2%} of {len(records)} sweeps")
    assert false <= 0.05
    assert all(r.decision.interval.covers == "seeds and objects" for r in records)


@pytest.mark.parametrize("name", CASES)
def test_large_effects_settle_at_the_first_look_and_small_ones_later(name):
    case = CASES[name]
    # Large: 150 first-look standard errors (t₁ at α/8 is 51: two seeds see little less; module docstring).
    large = _run(case, 150 * case.first_look_se(), EFFECT_SWEEPS, seed=2)
    at_first = sum(r.seeds == MIN_SEEDS and r.decision.verdict == "worse" for r in large) / len(large)
    small = _run(case, 5 * case.first_look_se(), EFFECT_SWEEPS, seed=3)
    settled = [r for r in small if r.decision.settled]
    print(f"\n{name}: large effects settled at the first look {at_first:.1%}; small effects settled "
          f"{len(settled) / len(small):.1%}, after {np.mean([r.seeds for r in small]):.2f} seeds on average")
    assert at_first >= 0.95
    assert settled and all(r.decision.verdict == "worse" for r in settled)  # higher score, mode min
    assert np.mean([r.seeds for r in small]) > np.mean([r.seeds for r in large])


def _banerjee(d: np.ndarray, alpha: float) -> np.ndarray:
    """Half-widths of :func:`sweeps.compare.sequential.two_way_interval` for d (n, S, O), vectorised over sweeps."""
    s, o = d.shape[1:]
    ms_seed, ms_object = o * d.mean(axis=2).var(axis=1, ddof=1), s * d.mean(axis=1).var(axis=1, ddof=1)
    t_seed, t_object = stats.t.ppf(1 - alpha / 2, [s - 1, o - 1])
    return np.sqrt((t_seed**2 * ms_seed + t_object**2 * ms_object) / (s * o))


def _satterthwaite(d: np.ndarray, alpha: float) -> np.ndarray:
    """The two-way ANOVA variance of the mean with one t at Satterthwaite's degrees of freedom."""
    s, o = d.shape[1:]
    seed_means, object_means, mean = d.mean(axis=2), d.mean(axis=1), d.mean(axis=(1, 2))
    ms_seed, ms_object = o * seed_means.var(axis=1, ddof=1), s * object_means.var(axis=1, ddof=1)
    residual = d - seed_means[:, :, None] - object_means[:, None, :] + mean[:, None, None]
    ms_residual = (residual**2).sum(axis=(1, 2)) / ((s - 1) * (o - 1))
    var = np.maximum(ms_seed + ms_object - ms_residual, np.maximum(ms_seed, ms_object))
    dof = var**2 / (ms_seed**2 / (s - 1) + ms_object**2 / (o - 1) + ms_residual**2 / ((s - 1) * (o - 1)))
    return stats.t.ppf(1 - alpha / 2, dof) * np.sqrt(var / (s * o))


def _seed_means(d: np.ndarray, alpha: float) -> np.ndarray:
    """A t-interval over the per-seed paired means (S − 1 degrees of freedom): objects held fixed."""
    s = d.shape[1]
    return stats.t.ppf(1 - alpha / 2, s - 1) * d.mean(axis=2).std(axis=1, ddof=1) / np.sqrt(s)


def _false_rate(half: Callable[[np.ndarray, float], np.ndarray], d: np.ndarray, alpha: float) -> float:
    """Share of null sweeps d (n, MAX_SEEDS, O) that some look's interval (±``half``) settles away from 0."""
    wrong = np.zeros(len(d), dtype=bool)
    for seeds in range(MIN_SEEDS, MAX_SEEDS + 1):
        wrong |= np.abs(d[:, :seeds].mean(axis=(1, 2))) > half(d[:, :seeds], alpha)
    return float(wrong.mean())


def test_the_rejected_intervals_each_break_the_null_rate_in_one_case():
    rates: dict[str, dict[str, float]] = {}
    for name, case in CASES.items():
        cells, references = _draw(case, 0.0, NULL_SWEEPS, np.random.default_rng(4))
        d = cells - references
        one_seed = np.mean([not (p.low <= 0.0 <= p.high) for p in (paired_bootstrap(x[0], np.zeros(OBJECTS))
                                                                   for x in d[:500])])
        rates[name] = {
            "chosen (Banerjee, Bonferroni)": _false_rate(_banerjee, d, 0.05 / LOOKS),
            "Banerjee, no correction": _false_rate(_banerjee, d, 0.05),
            "Satterthwaite, Bonferroni": _false_rate(_satterthwaite, d, 0.05 / LOOKS),
            "t over seed means, Bonferroni": _false_rate(_seed_means, d, 0.05 / LOOKS),
            "one seed, objects only": float(one_seed),
        }
    for name, found in rates.items():
        print(f"\n{name}: " + "; ".join(f"{k} {v:.1%}" for k, v in found.items()))
    assert all(found["chosen (Banerjee, Bonferroni)"] <= 0.05 for found in rates.values())
    for rejected in list(rates["seeds dominate"])[1:]:
        assert max(found[rejected] for found in rates.values()) > 0.05, rejected
    assert rates["seeds dominate"]["one seed, objects only"] > 0.3


# Hand-computed case: 3 seeds × 4 objects of differences d = cell − reference
#   seed 0: 1 2 3 2   (mean 2)      object means: 1 2 3 2  → var (ddof 1) = (1 + 0 + 1 + 0)/3 = 2/3
#   seed 1: 2 3 4 3   (mean 3)      seed means:   2 3 1    → var (ddof 1) = (0 + 1 + 1)/2 = 1
#   seed 2: 0 1 2 1   (mean 1)      grand mean 2
# MS_seed = O · 1 = 4, MS_object = S · 2/3 = 2. One look at 95 %: t₂(0.975) = 4.302653, t₃(0.975) = 3.182446,
# half = √((4.302653² · 4 + 3.182446² · 2) / 12) = √((74.0513 + 20.2559) / 12) = √7.85893 = 2.803379.
GRID = np.array([[1.0, 2, 3, 2], [2, 3, 4, 3], [0, 1, 2, 1]])


def _pair(grid: np.ndarray, shift: float = 0.0) -> tuple[dict, dict]:
    reference = {s: {f"o{o}": 10.0 * o + s for o in range(grid.shape[1])} for s in range(len(grid))}
    cell = {s: {k: v + grid[s, o] + shift for o, (k, v) in enumerate(reference[s].items())} for s in reference}
    return cell, reference


def test_interval_matches_the_hand_computation():
    got = decide(*_pair(GRID), mode="min", margin=None, look=1, looks=1)
    assert got.interval == SeedInterval(pytest.approx(2.0), pytest.approx(2 - 2.803379), pytest.approx(2 + 2.803379),
                                        3, 4, "seeds and objects")
    assert got.verdict == "open" and not got.settled
    assert got.interval.text() == "+2.00 [-0.80, +4.80]"
    # Four planned looks: each spends 0.05/4, t₂(0.99375) = 8.860, t₃(0.99375) = 5.392
    # → half = √((8.860² · 4 + 5.392² · 2) / 12) = √(314.0 + 58.15) / √12 = 5.569.
    wider = decide(*_pair(GRID), mode="min", margin=None, look=2, looks=4)
    assert wider.interval.high - wider.interval.mean == pytest.approx(5.569, abs=2e-3)


def test_verdicts_follow_the_mode_and_the_margin():
    shifted = _pair(GRID, shift=3.0)  # mean 5, interval [2.197, 7.803]: excludes 0
    assert decide(*shifted, mode="min", margin=None, look=1, looks=1).verdict == "worse"
    assert decide(*shifted, mode="max", margin=None, look=1, looks=1).verdict == "better"
    small = _pair(GRID / 100)  # mean 0.02, interval [-0.008, 0.048]
    assert decide(*small, mode="max", margin=0.05, look=1, looks=1).verdict == "level"
    assert decide(*small, mode="max", margin=0.04, look=1, looks=1).verdict == "open"
    assert decide(*small, mode="max", margin=None, look=1, looks=1).verdict == "open"


def test_one_seed_shows_the_object_interval_and_settles_nothing():
    cell, reference = _pair(GRID[:1] + 100.0)
    got = decide(cell, reference, mode="min", margin=1.0, look=1, looks=4)
    one = paired_bootstrap(GRID[0] + 100.0, np.zeros(4))
    assert got == Decision(SeedInterval(one.mean, one.low, one.high, 1, 4, "objects"), "open")


def test_only_shared_seeds_pair_and_other_objects_refuse():
    cell, reference = _pair(GRID)
    cell[7] = dict(cell[0])
    assert decide(cell, reference, mode="min", margin=None, look=1, looks=1).interval.seeds == 3
    with pytest.raises(UnpairedError, match="no training seed in common"):
        decide({5: cell[0]}, reference, mode="min", margin=None, look=1, looks=1)
    moved = {s: dict(v) for s, v in cell.items()}
    moved[1]["o9"] = moved[1].pop("o3")
    with pytest.raises(UnpairedError, match="seed 1 of the cell was evaluated on other objects"):
        decide(moved, reference, mode="min", margin=None, look=1, looks=1)


@pytest.mark.parametrize(("kwargs", "field"), [({"look": 0}, "look"), ({"look": 5}, "look"), ({"level": 1.0}, "level"),
                                               ({"margin": -0.1}, "margin")])
def test_bad_arguments_name_the_field(kwargs, field):
    args = {"mode": "min", "margin": None, "look": 1, "looks": 4} | kwargs
    with pytest.raises(ValueError, match=field):
        decide(*_pair(GRID), **args)


def test_record_text_says_settled_or_open():
    interval = SeedInterval(1.0, 0.5, 1.5, 2, 4, "seeds and objects")
    assert SettleRecord(2, Decision(interval, "better"), "settled").text() == "better, settled after 2 seeds"
    assert SettleRecord(5, Decision(interval, "open"), "max").text() == "open at 5 seeds"
    assert "Bonferroni" in FOOTNOTE and "Banerjee" in FOOTNOTE
