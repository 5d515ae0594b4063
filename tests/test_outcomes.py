"""How trials ended and the order a sweep lists them: grid order, Optuna's best first, the unstarted ones."""

from __future__ import annotations

from sweeps.compare.outcomes import TrialOutcome, finished, sweep_order, unstarted

OUTCOMES = [
    TrialOutcome("b · seed 0", "b", "ok", {"eval/f1": 0.4}),
    TrialOutcome("x · seed 0", "x", "failed"),
    TrialOutcome("a · seed 0", "a", "stopped", {"eval/f1": 0.6}),
    TrialOutcome("c · seed 0", "c", "ok", {"eval/f1": 0.5}),
]


def test_finished_keeps_ok_and_stopped_trials_in_order():
    assert [o.label for o in finished(OUTCOMES)] == ["b · seed 0", "a · seed 0", "c · seed 0"]
    assert [o.finished for o in OUTCOMES] == [True, False, True, True]


def test_a_grid_lists_its_trials_in_plan_order_and_unplanned_ones_last():
    plan = ["a · seed 0", "b · seed 0", "c · seed 0"]
    ordered = sorted(OUTCOMES, key=sweep_order(plan, "eval/f1", "max"))
    assert [o.label for o in ordered] == ["a · seed 0", "b · seed 0", "c · seed 0", "x · seed 0"]


def test_an_optuna_sweep_lists_the_best_first_and_trials_without_the_metric_last():
    by_max = sorted(OUTCOMES, key=sweep_order(None, "eval/f1", "max"))
    by_min = sorted(OUTCOMES, key=sweep_order(None, "eval/f1", "min"))
    assert [o.cell for o in by_max] == ["a", "c", "b", "x"]
    assert [o.cell for o in by_min] == ["b", "c", "a", "x"]


def test_unstarted_trials_are_the_planned_ones_without_an_outcome_that_the_next_round_would_start():
    plan = ["a · seed 0", "a · seed 1", "b · seed 0", "b · seed 1", "d · seed 0"]
    assert unstarted(plan, OUTCOMES) == ["a · seed 1", "b · seed 1", "d · seed 0"]
    assert unstarted(plan, OUTCOMES, next_round={"b · seed 1"}) == ["b · seed 1"]
