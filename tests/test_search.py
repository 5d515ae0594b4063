"""Search kinds: ``search.kind`` names a registered algorithm, a kind a user registers is planned, described
and handed to Tune like the shipped ones, and the Optuna kind samples the spec's typed space."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import optuna.distributions as od
import pytest
from ray.tune.search import Searcher
from ray.tune.search.optuna import OptunaSearch

from sweeps import run
from sweeps.execute import tuner
from sweeps.plan.describe import describe
from sweeps.plan.schema_base import SpecError
from sweeps.plan.search import SEARCHES, SearchKind, SearchSettings, optuna_distributions, search_kind
from sweeps.plan.spec import SpaceParam, Spec, load_spec
from sweeps.plan.trials import expand

SPACE = {"priors.lambda_3d": {"type": "log_float", "low": 1e-3, "high": 10.0}}


class _LowBounds(Searcher):
    """Proposes the low end of every dimension: the smallest real Tune searcher."""

    def __init__(self, space: dict[str, Any], metric: str, mode: str) -> None:
        super().__init__(metric=metric, mode=mode)
        self.space = space

    def suggest(self, trial_id: str) -> dict[str, Any]:
        return {key: p.low for key, p in self.space.items()}

    def on_trial_complete(self, trial_id: str, result: dict | None = None, error: bool = False) -> None:
        pass


class LowBounds(SearchKind):
    """What a user adds: one class and one entry in SEARCHES."""

    name = "low_bounds"
    samples_space = True

    def describe(self, search: SearchSettings) -> str:
        return "the low bounds"

    def tune_searcher(self, search: SearchSettings, metric: str, mode: str, study: str) -> Searcher:
        return _LowBounds(dict(search.space), metric, mode)


def test_an_unknown_kind_is_refused_naming_the_field_and_the_registered_kinds(tmp_path, capsys):
    path = tmp_path / "t.yaml"
    path.write_text("name: t\nsearch: {kind: hyperopt, space: {priors.lambda_3d: {type: float, low: 0.1, high: 1}}}\n")
    with pytest.raises(SpecError, match=r"search\.kind: .*unknown search 'hyperopt'; allowed: grid, optuna"):
        load_spec(path)
    assert run.main([str(path), "--smoke", "--dry-run"]) == 2
    assert "allowed: grid, optuna" in capsys.readouterr().err
    with pytest.raises(ValueError, match="allowed: grid, optuna"):
        search_kind("hyperopt")


def test_a_grid_takes_no_space_and_a_sampled_kind_needs_one():
    with pytest.raises(ValueError, match=r"search.space: only used by a search that samples it \(optuna\)"):
        Spec.model_validate({"name": "t", "grid": {"priors.point_size": [0.04]}, "search": {"space": SPACE}})
    with pytest.raises(ValueError, match="search.kind optuna samples it; give at least one dimension"):
        Spec.model_validate({"name": "t", "search": {"kind": "optuna"}})
    assert not Spec.model_validate({"name": "t", "grid": {"priors.point_size": [0.04]}}).search.sampled


def test_a_registered_kind_is_planned_described_and_handed_to_tune(monkeypatch):
    monkeypatch.setitem(SEARCHES, LowBounds.name, LowBounds())
    spec = Spec.model_validate({"name": "t", "search": {"kind": "low_bounds", "num_samples": 3, "space": SPACE}})
    assert spec.search.sampled
    plan = expand(spec, "smoke")
    assert plan.cells == () and plan.num_trials == 3
    assert "search: the low bounds, 3 trials, seed 0, over:" in describe(plan, cpus=2.0, gpus=0.0)
    param_space, searcher, samples = tuner._search(plan, sweep_run=None, budget=None)
    assert param_space == {} and samples == 3 and isinstance(searcher, _LowBounds)
    assert (searcher.metric, searcher.mode) == ("eval/f1", "max")
    proposed = searcher.suggest("t1")
    assert proposed == {"priors.lambda_3d": 1e-3}
    assert plan.sampled_cell(proposed).config.priors.lambda_3d == 1e-3


def test_the_optuna_kind_samples_the_typed_space():
    spec = load_spec(Path(__file__).resolve().parents[1] / "sweeps" / "lambda.yaml")
    searcher = search_kind("optuna").tune_searcher(spec.search, "eval/f1", "max", "study-1")
    assert isinstance(searcher, OptunaSearch)
    assert (searcher.metric, searcher.mode) == ("eval/f1", "max")
    params = {
        "x": {"type": "log_float", "low": 1e-3, "high": 10.0},
        "n": {"type": "int", "low": 2, "high": 8, "step": 2},
        "f": {"type": "float", "low": 0.0, "high": 1.0, "step": 0.25},
        "c": {"type": "categorical", "choices": ["contour", "depth"]},
    }
    assert optuna_distributions({k: SpaceParam.model_validate(v) for k, v in params.items()}) == {
        "x": od.FloatDistribution(1e-3, 10.0, log=True), "n": od.IntDistribution(2, 8, step=2),
        "f": od.FloatDistribution(0.0, 1.0, step=0.25), "c": od.CategoricalDistribution(["contour", "depth"])}
