"""The search algorithms a spec may name as ``search.kind``: a registry, as ``cdm.data.DATASETS`` is for data sets.

A kind either runs the spec's grid of cells, one trial each (``grid``), or draws ``search.num_samples``
trials from the spec's typed ``search.space`` with a Ray Tune searcher it builds (``optuna``).

Adding one (Ray Tune also wraps HyperOpt, Ax, BayesOpt, Nevergrad, …) is a :class:`SearchKind` subclass
here and one entry in :data:`SEARCHES`: ``search.kind`` then accepts its name, ``--dry-run`` and the
trial count treat it as a sampled search, and :func:`sweeps.execute.tuner.run_sweep` hands Tune the
searcher it builds.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, Protocol

__all__ = [
    "SEARCHES",
    "GridSearch",
    "OptunaSampler",
    "SearchKind",
    "SearchSettings",
    "optuna_distributions",
    "search_kind",
]


class SearchSettings(Protocol):
    """The fields of a spec's ``search:`` section a kind reads (:class:`sweeps.plan.spec.Search`)."""

    sampler: str
    seed: int
    space: Mapping[str, Any]
    """Dotted config field → :class:`sweeps.plan.spec.SpaceParam` (``type``, ``low``, ``high``, ``step``,
    ``choices``)."""


class SearchKind:
    """One algorithm ``search.kind`` may name."""

    name: ClassVar[str]
    samples_space: ClassVar[bool]
    """True: ``search.num_samples`` trials drawn from ``search.space`` at one seed; False: the grid's cells × seeds."""

    def describe(self, search: SearchSettings) -> str:
        """How ``--dry-run`` names this search (e.g. "Optuna tpe (seed 0)")."""
        return self.name

    def tune_searcher(self, search: SearchSettings, metric: str, mode: str, study: str) -> Any:
        """The ``ray.tune.search.Searcher`` that proposes this kind's trials, optimising ``metric`` (``mode``
        ``"min"``/``"max"``); ``study`` is a name unique to this sweep. A kind that samples must build one."""
        raise NotImplementedError(f"search kind {self.name!r} samples search.space but builds no Tune searcher")


class GridSearch(SearchKind):
    """Every cell of the spec's ``grid`` and ``cells``, at each of its seeds: Tune's grid search over their labels."""

    name = "grid"
    samples_space = False


class OptunaSampler(SearchKind):
    """Optuna's TPE (``search.sampler: tpe``, the default) or random sampler over ``search.space``, seeded
    by ``search.seed``; Ray Tune's ``OptunaSearch`` asks it for each next trial."""

    name = "optuna"
    samples_space = True

    def describe(self, search: SearchSettings) -> str:
        return f"Optuna {search.sampler} (seed {search.seed})"

    def tune_searcher(self, search: SearchSettings, metric: str, mode: str, study: str) -> Any:
        import optuna
        from ray.tune.search.optuna import OptunaSearch

        sampler = (optuna.samplers.TPESampler if search.sampler == "tpe" else optuna.samplers.RandomSampler)(
            seed=search.seed
        )
        # Given its own space, OptunaSearch never receives TuneConfig's metric/mode: pass them here too.
        return OptunaSearch(space=optuna_distributions(search.space), metric=metric, mode=mode, sampler=sampler,
                            study_name=study)


SEARCHES: dict[str, SearchKind] = {kind.name: kind for kind in (GridSearch(), OptunaSampler())}
"""Search kinds by ``search.kind`` name."""


def search_kind(name: str) -> SearchKind:
    """The registered kind called ``name``.

    Raises:
        ValueError: no kind of that name; the message lists the registered ones.
    """
    if name not in SEARCHES:
        raise ValueError(f"unknown search {name!r}; allowed: {', '.join(SEARCHES)}")
    return SEARCHES[name]


def optuna_distributions(space: Mapping[str, Any]) -> dict[str, Any]:
    """A spec's ``search.space`` as Optuna distributions (what :class:`OptunaSampler` samples, what the
    report's Optuna plots read)."""
    import optuna.distributions as od

    out: dict[str, Any] = {}
    for key, p in space.items():
        if p.type == "categorical":
            out[key] = od.CategoricalDistribution(p.choices)
        elif p.type == "int":
            out[key] = od.IntDistribution(int(p.low), int(p.high), step=int(p.step or 1))
        else:
            out[key] = od.FloatDistribution(p.low, p.high, log=p.type == "log_float", step=p.step)
    return out
