"""Paired bootstrap: equal to a direct numpy loop, golden numbers, verdicts, refusal to pair."""

from __future__ import annotations

import numpy as np
import pytest

from sweeps.compare.bootstrap import PairedDifference, UnpairedError, compare, paired_bootstrap, per_object_means

A = [10.13, 12.57, 9.02, 14.31, 11.0, 8.46, 13.09, 10.55]
B = [11.0, 13.0, 9.5, 15.5, 11.0, 9.0, 14.5, 11.5]


def test_matches_a_direct_numpy_loop():
    got = paired_bootstrap(A, B, resamples=1000, seed=3)
    rng = np.random.default_rng(3)
    d = np.array(A) - np.array(B)
    draws = rng.integers(0, len(d), size=(1000, len(d)))
    means = [float(np.mean([d[i] for i in row])) for row in draws]
    assert got.mean == pytest.approx(float(np.mean(d)))
    assert got.low == pytest.approx(float(np.percentile(means, 2.5)))
    assert got.high == pytest.approx(float(np.percentile(means, 97.5)))
    assert got.n == 8


def test_golden_numbers_and_seeded():
    got = paired_bootstrap(A, B)  # 2,000 resamples, seed 0
    assert (round(got.mean, 5), round(got.low, 4), round(got.high, 4)) == (-0.73375, -1.0176, -0.4212)
    assert paired_bootstrap(A, B) == got
    assert paired_bootstrap(A, B, seed=1) != got


def test_verdicts_follow_the_metric_direction():
    lower = PairedDifference(-2.0, -3.0, -1.0, 10)
    assert lower.verdict("min") == "better" and lower.verdict("max") == "worse"
    higher = PairedDifference(0.02, 0.01, 0.03, 10)
    assert higher.verdict("max") == "better" and higher.verdict("min") == "worse"
    assert PairedDifference(0.1, -0.2, 0.4, 10).verdict("min") == "no clear difference"
    assert PairedDifference(0.0, 0.0, 0.0, 10).verdict("max") == "no clear difference"


def test_seeds_are_averaged_per_object_and_only_shared_objects_count():
    seed0 = [{"object_id": "a", "cd": 1.0}, {"object_id": "b", "cd": 3.0}]
    seed1 = [{"object_id": "a", "cd": 2.0}]
    assert per_object_means([seed0, seed1], "cd") == {"a": 1.5}


def test_different_objects_or_evaluation_sets_refuse_to_pair():
    with pytest.raises(UnpairedError, match="x and y were evaluated on different objects"):
        compare({"a": 1.0, "b": 2.0}, {"a": 1.0, "c": 2.0}, ("x", "y"))
    one = per_object_means([[{"object_id": "a", "eval_set": "f00", "cd": 1.0}]], "cd")
    other = per_object_means([[{"object_id": "a", "eval_set": "f01", "cd": 1.0}]], "cd")
    with pytest.raises(UnpairedError):
        compare(one, other, ("x", "y"))
