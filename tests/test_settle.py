"""Seeds until settled (sweeps/execute/settle/): the rule round by round on planted scores, the entry point's
dry-run lines and final round; no Ray, no MLflow."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sweeps.compare.outcomes import TrialOutcome
from sweeps.execute.settle import BUDGET_TAG, UntilSettled
from sweeps.execute.settle.rule import next_round, object_scores, outcome_results
from sweeps.plan.budget import SeedBudget, check_budget, parse_budget
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import Spec
from sweeps.plan.trials import SweepPlan, expand

OBJECTS = [f"obj{i:02d}" for i in range(20)]


def _plan(cells: list[dict], low: int = 2, high: int = 4, margin: float | None = None, **extra) -> SweepPlan:
    spec = Spec.model_validate({"name": "t", "cells": cells, "seeds": {"min": low, "max": high, "until": "settled"},
                                "settle": {"margin": margin}, **extra})
    return expand(spec, "smoke")


REFERENCE_NULL_LARGE = [{"label": "ref"}, {"label": "null", "set": {"eval.save_clouds": 1}},
                        {"label": "large", "set": {"eval.f1_threshold": 0.05}}]
EFFECT = {"ref": 0.0, "null": 0.0, "large": 0.5}


def _score(label: str) -> dict[str, float]:
    """Per-object F1 of a trial: an object term, a seed term shared by every cell (same training seed), the
    cell's planted effect; the null cell scores exactly what the reference scores at each seed."""
    cell, seed = label.split(" · seed ")
    rng = np.random.default_rng(int(seed))
    shift = rng.normal(0.0, 0.05)
    return {o: 0.3 + 0.01 * i + shift + EFFECT[cell] for i, o in enumerate(OBJECTS)}


def _drive(plan: SweepPlan, trials: int | None = None, out_of_time: bool = False) -> list[tuple[str, ...]]:
    """The searcher's loop without Tune: start what the rule says, finish it, ask again; the rounds started."""
    started: set[str] = set()
    results: dict[str, dict[str, float] | None] = {}
    rounds = []
    budget = None if trials is None else SeedBudget(trials=trials)
    while not (now := next_round(plan, started, results, budget, out_of_time)).finished:
        rounds.append(now.start)
        started |= set(now.start)
        results |= {label: _score(label) for label in now.start}
    return rounds


def test_a_large_effect_settles_in_round_1_and_a_null_cell_runs_to_max_with_the_reference():
    plan = _plan(REFERENCE_NULL_LARGE)
    assert _drive(plan) == [
        tuple(f"{c} · seed {s}" for c in ("ref", "null", "large") for s in (0, 1)),
        ("ref · seed 2", "null · seed 2"),
        ("ref · seed 3", "null · seed 3"),
    ]
    started = {c.label for c in plan.cells} - {"large · seed 2", "large · seed 3"}
    final = next_round(plan, started, {label: _score(label) for label in started})
    assert final.finished and set(final.records) == {"null", "large"}
    assert (final.records["large"].seeds, final.records["large"].reason, final.records["large"].text()) == \
        (2, "settled", "better, settled after 2 seeds")
    null = final.records["null"]
    assert (null.seeds, null.reason, null.text()) == (4, "max", "open at 4 seeds")
    assert null.decision.interval.low == null.decision.interval.high == 0.0 and null.decision.interval.seeds == 4


def test_a_margin_settles_the_null_cell_as_level_at_the_first_look():
    plan = _plan(REFERENCE_NULL_LARGE, margin=0.01)
    assert len(_drive(plan)) == 1
    started = {label for label in (c.label for c in plan.cells) if int(label[-1]) < 2}
    records = next_round(plan, started, {label: _score(label) for label in started}).records
    assert records["null"].text() == "level, settled after 2 seeds"


@pytest.mark.parametrize(("trials", "out_of_time", "seeds"), [
    (8, False, 3),  # round 1 takes 6; the null cell's third seed and the reference's take the last 2
    (7, False, 2),  # one left: the null cell's next seed needs the reference's too
    (None, True, 2),
])
def test_the_budget_stops_open_cells_with_reason_budget(trials, out_of_time, seeds):
    plan = _plan(REFERENCE_NULL_LARGE)
    rounds = _drive(plan, trials, out_of_time)
    started = {label for r in rounds for label in r}
    assert len(started) == 6 + 2 * (seeds - 2)
    records = next_round(plan, started, {label: _score(label) for label in started},
                         None if trials is None else SeedBudget(trials=trials), out_of_time).records
    assert (records["null"].seeds, records["null"].reason) == (seeds, "budget")
    assert records["large"].reason == "settled"


def test_a_failed_seed_ends_its_cell_without_a_record_and_the_others_go_on():
    plan = _plan(REFERENCE_NULL_LARGE)
    first = next_round(plan, set(), {}).start
    results = {label: (None if label == "large · seed 1" else _score(label)) for label in first}
    now = next_round(plan, set(first), results)
    assert now.start == ("ref · seed 2", "null · seed 2") and "large" not in now.records


def test_the_reference_is_whichever_cell_compare_to_names():
    plan = _plan(REFERENCE_NULL_LARGE, compare_to="null")
    first = next_round(plan, set(), {}).start
    now = next_round(plan, set(first), {label: _score(label) for label in first})
    # ref and null score alike: ref stays open and takes the next seed, with null (its reference) beside it.
    assert now.start == ("ref · seed 2", "null · seed 2") and set(now.records) == {"large"}


def test_rows_of_a_trial_become_scores_of_the_metric_and_outcomes_become_started_and_results():
    rows = [
        {"object_id": "a", "category": "chair", "f1": 0.5, "cd": 3.0},
        {"object_id": "b", "category": "table", "f1": 0.25, "cd": 4.0},
    ]
    assert object_scores(rows, "eval/f1") == {"a": 0.5, "b": 0.25}
    assert object_scores(rows, "eval/cd/table") == {"b": 4.0}
    assert object_scores(rows, "train/loss") == {}
    plan = _plan(REFERENCE_NULL_LARGE)
    outcomes = [
        TrialOutcome("ref · seed 0", "ref", "ok", objects=tuple(rows)),
        TrialOutcome("ref · seed 1", "ref", "failed"),
        TrialOutcome("null · seed 0", "null", "pending"),
        TrialOutcome("null · seed 1", "null", "stopped", objects=tuple(rows)),
    ]
    started, results = outcome_results(plan, outcomes)
    assert started == {"ref · seed 0", "ref · seed 1", "null · seed 0", "null · seed 1"}
    assert results == {"ref · seed 0": {"a": 0.5, "b": 0.25}, "ref · seed 1": None}


def test_a_budget_must_fit_round_1_and_needs_seeds_until_settled(tmp_path):
    plan = _plan(REFERENCE_NULL_LARGE)
    check_budget(plan, parse_budget("6"))
    check_budget(plan, parse_budget("45m"))
    with pytest.raises(
        SpecError, match=r"--budget 5: round 1 alone runs 6 trials \(every cell at 2 seeds\); give at least 6"
    ):
        check_budget(plan, SeedBudget(trials=5))
    fixed = expand(Spec.model_validate({"name": "t", "cells": REFERENCE_NULL_LARGE, "seeds": [0, 1]}), "smoke")
    with pytest.raises(SpecError, match="--budget: only seeds run until settled spend a budget; add --until-settled"):
        check_budget(fixed, SeedBudget(seconds=60.0))
    assert UntilSettled(fixed).lines() == []
    lines = UntilSettled(plan, SeedBudget(seconds=2700.0)).lines()
    assert lines[0] == (
        "search: grid, seeds until settled: round 1 = 3 cells × 2 seeds = 6 trials; worst case 12 trials "
        "(3 cells × 4 seeds, 3 looks)"
    )
    assert "(better/worse) (no settle.margin: no level verdict); else" in lines[1] and "Bonferroni" in lines[2]
    assert lines[3] == "budget: 45 min wall time"


def test_the_final_round_reads_outcomes_and_the_parent_runs_budget_tag_and_writes_settle_json(tmp_path):
    plan = _plan(REFERENCE_NULL_LARGE)
    rule = UntilSettled(plan, SeedBudget(trials=12))
    rows = {label: tuple({"object_id": o, "f1": v} for o, v in _score(label).items())
            for label in next_round(plan, set(), {}).start}
    outcomes = [TrialOutcome(label, label.split(" · ")[0], "ok", objects=r) for label, r in rows.items()]
    open_round = rule.final(outcomes, {})
    assert open_round.start == ("ref · seed 2", "null · seed 2") and set(open_round.records) == {"large"}
    ended = rule.final(outcomes, {BUDGET_TAG: "60"})
    assert ended.start == () and (ended.records["null"].seeds, ended.records["null"].reason) == (2, "budget")
    written = json.loads(rule.write_json(tmp_path / "settle.json", ended.records).read_text())
    assert written["budget"] == "12 trials"
    assert {k: v for k, v in written["cells"]["large"].items() if k != "interval"} == {
        "seeds": 2, "verdict": "better", "reason": "settled", "text": "better, settled after 2 seeds"}
    assert written["cells"]["null"]["interval"] == {"mean": 0.0, "low": 0.0, "high": 0.0, "objects": 20,
                                                    "covers": "seeds and objects"}
