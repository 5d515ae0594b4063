"""Sweep plan: a validated spec expanded into its trials, each with its validated ``cdm.Config``, before Ray starts.

One trial's config is resolved in this order, later wins::

    cdm defaults < shared profile overrides < spec base < spec profile overrides
      < the profile's fields for the run's data set (``datasets.<data.kind>``) < the spec's paper run
      on that data set (``--profile paper --set data.root=...``) < budget (train.steps, train.eval_every)
      < cell values < seed (train.seed) < --set

``train.threads`` is the profile's CPUs per worker unless a level above sets it (then that value stays).

A sequential spec's cells are built up to its ``max`` seeds, so every trial its searcher may start has its
label and config before Ray starts.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel

from cdm.config import Config, ConfigError, TrainConfig, load_config
from cdm.metric_names import COMPUTE_METRIC, COMPUTE_UNIT, F1, metric_names
from sweeps.plan.profiles import Budget, Profile, Resources, load_profiles
from sweeps.plan.schema_base import SpecError, field_error
from sweeps.plan.spec import DatasetRun, ExplicitCell, PaperRow, SequentialSeeds, Spec

__all__ = [
    "SEED_MARK", "Cell", "ResolvedProfile", "SweepPlan", "cell_name", "expand", "resolve_profile", "split_label",
    "trial_label",
]

# Paper notation for readable cell names; other fields use their last dotted part.
_SHORT_NAMES = {"priors.num_views": "H", "priors.lambda_3d": "λ", "data.categories": "categories"}


@dataclass(frozen=True)
class ResolvedProfile:
    name: str
    description: str
    steps: int
    eval_every: int
    overrides: dict[str, Any]
    resources: Resources
    num_samples: int | None
    datasets: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Fields set when a run reads one of these data sets (:attr:`sweeps.plan.profiles.Profile.datasets`)."""
    compute_s: float | None = None
    """Seconds of compute per trial (:attr:`sweeps.plan.profiles.Budget.compute_s`); None: a budget in steps."""
    eval_every_s: float | None = None

    @property
    def time_axis(self) -> tuple[str, float, float]:
        """ASHA's time attribute, a trial's whole budget and the interval of its evaluations in that unit:
        ``("train/compute_s", seconds, seconds)`` for a budget in compute, else ``("step", steps, eval_every)``."""
        if self.compute_s is None:
            return "step", self.steps, self.eval_every
        return COMPUTE_METRIC, self.compute_s, self.eval_every_s or self.compute_s

    def budget_text(self) -> str:
        """The budget in words, with its unit (the dry run's and the results table's line)."""
        if self.compute_s is None:
            return f"{self.steps} steps, evaluation every {self.eval_every}"
        return (f"{self.compute_s:g} s of compute per trial ({COMPUTE_UNIT}), evaluation every "
                f"{self.time_axis[2]:g} s of it, at most {self.steps} steps")

    def completed(self, step: int, result: Mapping[str, Any]) -> bool:
        """Whether a trial whose last report is ``result`` at ``step`` spent its whole budget (not stopped early)."""
        if self.compute_s is not None and float(result.get(COMPUTE_METRIC, 0.0)) >= self.compute_s:
            return True
        return step >= self.steps


@dataclass(frozen=True)
class Cell:
    """One trial of a grid sweep: a cell of the grid at one seed."""

    name: str
    """Readable cell name without the seed, e.g. ``point_size=0.04`` (an explicit cell's label)."""
    label: str
    """Unique trial label, ``<name> · seed <seed>``; names the MLflow child run."""
    values: dict[str, Any]
    seed: int
    config: Config
    """The trial's validated config: every override resolved, in the order this module's docstring gives."""
    paper_label: str | None = None
    paper: dict[str, float] = field(default_factory=dict)
    group: str = field(init=False)
    """The swept values alone (``0.04``, ``10 · 0.02``): the short name MLflow's runs view groups the
    seeds of this cell under, narrow enough for its name column. Set here, with the cell, so a trial reads
    it without calling back into the plan."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "group", " · ".join(_fmt_value(v) for v in self.values.values()) or self.name)


@dataclass(frozen=True)
class SweepPlan:
    spec: Spec
    profile: ResolvedProfile
    fixed: dict[str, Any]
    """Overrides shared by every trial (profile, base, budget, threads); cells and seeds add to them."""
    sets: dict[str, Any]
    cells: tuple[Cell, ...]
    """Every trial of a grid search; empty for Optuna (trials are sampled while the sweep runs)."""
    metric_names: tuple[str, ...]
    grid_trials: int | None = None
    """Trials of a grid expanded with ``keep`` (:func:`expand`), when ``cells`` holds only the first of them."""

    @property
    def num_trials(self) -> int:
        """Trials of the sweep; a sequential sweep's worst case (every cell at ``max`` seeds)."""
        if self.spec.search.sampled:
            return self.profile.num_samples or self.spec.search.num_samples
        return len(self.cells) if self.grid_trials is None else self.grid_trials

    @property
    def swept(self) -> frozenset[str]:
        """Config fields the trials vary (the grid, explicit cells, a sampled search's space): never one of
        the settings every trial shares, whatever ``fixed`` holds for them before a cell sets its own."""
        s = self.spec
        return frozenset({*s.grid, *s.search.space, *(k for c in s.cells for k in c.set)})

    @property
    def sequential(self) -> SequentialSeeds | None:
        """The spec's rule when its seeds run until settled (:class:`sweeps.plan.spec.SequentialSeeds`), else None."""
        return self.spec.sequential

    @property
    def rounds(self) -> int:
        """Rounds of the sweep at most: a sequential sweep's planned looks, else 1."""
        return self.sequential.looks if self.sequential else 1

    def round_of(self, cell: Cell) -> int:
        """The round ``cell`` runs in: 1 for every seed of a fixed list and the first ``min`` of a sequential
        sweep, then one round per further seed."""
        rule = self.sequential
        index = self.spec.seed_values.index(cell.seed)
        return 1 if rule is None or index < rule.min else index - rule.min + 2

    @property
    def first_round(self) -> tuple[Cell, ...]:
        """The trials that run whatever the results: every trial of a fixed list, round 1 of a sequential sweep."""
        return tuple(c for c in self.cells if self.round_of(c) == 1)

    def completed(self, label: str, step: int, result: Mapping[str, Any]) -> bool:
        """Whether trial ``label``, last reporting ``result`` at ``step``, ran to the end of its budget."""
        return step >= self.last_step(label) or self.profile.completed(step, result)

    def last_step(self, label: str) -> int:
        """The step a trial of ``label`` ends at when it runs to the end: 0 for a cell that only scores its
        starting weights (``eval.only``: PC²'s released weights), else the profile's budget."""
        cell = self.grid_cell(label)
        return 0 if cell is not None and cell.config.eval.only else self.profile.steps

    def grid_cell(self, label: str) -> Cell | None:
        """The grid cell of this trial label (its config built by :func:`expand`); None in an Optuna sweep."""
        return next((c for c in self.cells if c.label == label), None)

    def shared_config(self, **more: Any) -> Config:
        """The config of the settings every trial shares (``fixed``, then ``more``, then ``--set``): what stands
        for an Optuna plan's trials before any is sampled."""
        return load_config(None, {**self.fixed, **more, **self.sets})

    @property
    def configs(self) -> list[Config]:
        """Every grid trial's config, or for an Optuna plan the one of :meth:`shared_config`."""
        return [c.config for c in self.cells] or [self.shared_config()]

    def f1_threshold(self, label: str, drawn: Mapping[str, Any]) -> float:
        """The trial ``label``'s ``eval.f1_threshold``, worked out here alone: what the trial drew or logged
        (``drawn``: a sampled trial's Tune config, or a run's params), else its grid cell's config, else
        the plan's shared config."""
        if "eval.f1_threshold" in drawn:
            return float(drawn["eval.f1_threshold"])
        cell = self.grid_cell(label)
        return (cell.config if cell else self.shared_config()).eval.f1_threshold

    def names(self, tune_config: Mapping[str, Any]) -> tuple[str, str]:
        """(cell name, trial label) of a Tune config, without resolving its config: for the driver's callbacks."""
        if not self.spec.search.sampled:
            cell = self.grid_cell(tune_config["cell"])
            return cell.name, cell.label
        name = cell_name({k: tune_config[k] for k in self.spec.search.space})
        return name, trial_label(name, self.spec.seed_values[0])

    def sampled_cell(self, tune_config: Mapping[str, Any]) -> Cell:
        """The trial of a sampled search's values (``{"priors.lambda_3d": 0.012}``), its config built here, once,
        in the trial that runs it (the values come from the searcher, not the plan)."""
        name, label = self.names(tune_config)
        values, seed = {k: tune_config[k] for k in self.spec.search.space}, self.spec.seed_values[0]
        return Cell(name, label, values, seed, self.shared_config(**values, **{"train.seed": seed}))

    def label(self, tune_config: Mapping[str, Any]) -> str:
        """The trial label of a Tune config (:meth:`names`)."""
        return self.names(tune_config)[1]


def _patch(model: BaseModel, patch: BaseModel) -> dict[str, Any]:
    return {**model.model_dump(exclude_unset=True), **patch.model_dump(exclude_unset=True)}


def resolve_profile(spec: Spec, name: str, shared: dict[str, Profile]) -> ResolvedProfile:
    if name not in shared and name not in spec.profiles:
        raise SpecError(f"profile {name!r}: unknown; available: {', '.join(sorted({*shared, *spec.profiles}))}")
    base = shared.get(name, Profile())
    local = spec.profiles.get(name, Profile())
    budget = Budget.model_validate(_patch(base.budget, local.budget))
    defaults = TrainConfig()
    resources = Resources.model_validate(
        {**_patch(base.resources, spec.resources), **local.resources.model_dump(exclude_unset=True)}
    )
    return ResolvedProfile(
        name=name,
        description=local.description or base.description,
        steps=defaults.steps if budget.steps is None else budget.steps,
        eval_every=defaults.eval_every if budget.eval_every is None else budget.eval_every,
        compute_s=budget.compute_s,
        eval_every_s=budget.eval_every_s,
        overrides={**base.overrides, **spec.base, **local.overrides},
        resources=resources,
        num_samples=local.num_samples or base.num_samples,
        datasets={
            d: {**base.datasets.get(d, {}), **local.datasets.get(d, {})} for d in {*base.datasets, *local.datasets}
        },
    )


def _fmt_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "+".join(str(v) for v in value) or "all"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


SEED_MARK = " · seed "
"""Between a trial label's cell name and its seed (``point_size=0.04 · seed 1``)."""


def trial_label(name: str, seed: int) -> str:
    """A trial's label, its MLflow child run's name: ``<cell name> · seed <seed>``."""
    return f"{name}{SEED_MARK}{seed}"


def split_label(label: str) -> tuple[str, str | None]:
    """``(cell name, seed)`` of a trial label; the seed is None for a label without one."""
    name, mark, seed = label.rpartition(SEED_MARK)
    return (name, seed) if mark else (label, None)


def cell_name(values: dict[str, Any]) -> str:
    """Readable name of swept ``values``: ``point_size=0.04 · H=10`` (paper notation where it has one)."""
    return " · ".join(f"{_SHORT_NAMES.get(k, k.split('.')[-1])}={_fmt_value(v)}" for k, v in values.items())


def _cell_values(spec: Spec) -> Iterator[tuple[str, dict[str, Any]]]:
    """(name, swept values) per cell, one at a time: explicit cells crossed with the grid, minus excluded
    combinations."""
    keys = list(spec.grid)
    for cell in spec.cells or [ExplicitCell(label="")]:
        for vals in itertools.product(*spec.grid.values()):
            combo = dict(zip(keys, vals))
            if not any(all(combo[k] == v for k, v in rule.items()) for rule in spec.exclude):
                yield " · ".join(p for p in (cell.label, cell_name(combo)) if p), {**cell.set, **combo}


def _build(overrides: dict[str, Any], where: str) -> Config:
    try:
        return load_config(None, overrides)
    except ConfigError as exc:
        raise SpecError(f"{where}: {exc}") from None


def _matches(row: PaperRow, config: Config) -> bool:
    flat = config.flat()
    return all(_same(flat[k], v) for k, v in row.when.items())


def _same(actual: Any, wanted: Any) -> bool:
    if isinstance(actual, float) and isinstance(wanted, (int, float)):
        return math.isclose(actual, wanted, rel_tol=1e-9)
    if isinstance(actual, (list, tuple)) and isinstance(wanted, (list, tuple)):
        return list(actual) == list(wanted)
    return actual == wanted


def _metric_names(cfg: Config) -> set[str]:
    from cdm.data import list_categories

    try:
        return set(metric_names(list_categories(cfg)))
    except ValueError as exc:
        raise SpecError(str(exc)) from None


def _check_metric(spec: Spec, names: set[str]) -> tuple[str, ...]:
    if spec.metric.name not in names:
        headline = sorted(n for n in names if n.count("/") == 1)
        raise SpecError(f"metric.name: {spec.metric.name!r} is not reported by the trainer; choose one of "
                        f"{', '.join(headline)} or a per-category name like {F1.key}/<category>")
    return tuple(sorted(names))


def _dataset_run(spec: Spec, profile: str, sets: dict[str, Any]) -> DatasetRun | None:
    """The paper's run on the data set ``--set data.root`` points at (paper profile only); sets
    ``data.kind`` in ``sets`` when the spec names one data set and ``--set`` gives none."""
    if profile != "paper" or "data.root" not in sets or not spec.datasets:
        return None
    if "data.kind" not in sets:
        if len(spec.datasets) > 1:
            raise SpecError(
                f"--set data.kind: this table ran on {' and '.join(spec.datasets)}; say which data.root holds"
            )
        sets["data.kind"] = next(iter(spec.datasets))
    return spec.datasets.get(sets["data.kind"])


def _shared_values(
    spec: Spec, profile: str, prof: ResolvedProfile, sets: dict[str, Any]
) -> tuple[Spec, dict[str, Any]]:
    """The values every trial shares (the profile's, its data set's, a data-set run's, the budget) checked
    with ``sets`` on top, and the spec with a data-set run's grid added.

    Raises:
        SpecError: naming ``--set`` when a ``--set`` value's field is rejected, else the profile.
    """
    run = _dataset_run(spec, profile, sets)
    if run is not None:
        spec = spec.model_copy(update={"grid": {**spec.grid, **run.grid}})
    kind = sets.get("data.kind", prof.overrides.get("data.kind"))
    fixed = {
        **prof.overrides,
        **prof.datasets.get(kind, {}),
        **(run.overrides if run else {}),
        "train.steps": prof.steps,
        "train.eval_every": prof.eval_every,
        "train.compute_budget_s": prof.compute_s,
        "train.eval_every_s": prof.eval_every_s,
    }
    fixed.setdefault("train.threads", max(1, int(prof.resources.cpus_per_worker)))
    try:
        load_config(None, {**fixed, **sets})
    except ConfigError as exc:  # a --set value's own field is the --set's error, not the profile's
        # A shared value may need what the cells give (model.init_from's {category}, the data.categories of
        # each cell): checked with the first cell's values, it stands; every cell is checked on its own later.
        if not _holds_with_a_cell(spec, {**fixed, **sets}):
            where = "--set" if any(f"{key}:" in str(exc) for key in sets) else f"profile {profile}"
            raise SpecError(f"{where}: {exc}") from None
    return spec, fixed


def _holds_with_a_cell(spec: Spec, shared: dict[str, Any]) -> bool:
    """Whether ``shared`` makes a config with the first grid cell's values (cells win, as in a trial)."""
    values = next(_cell_values(spec), ("", {}))[1] if not spec.search.sampled else {}
    try:
        load_config(None, {**shared, **values})
    except ConfigError:
        return False
    return bool(values)


def expand(
    spec: Spec,
    profile: str = "local",
    sets: dict[str, Any] | None = None,
    shared: dict[str, Profile] | None = None,
    keep: int | None = None,
    each: Callable[[int, Cell], None] | None = None,
) -> SweepPlan:
    """Resolve ``profile`` and ``--set`` values and build every cell's config.

    ``keep``: hold only a grid's first ``keep`` cells in the plan; every cell is still built and checked,
    one at a time (a dry-run of 10⁶ cells would otherwise hold gigabytes of configs). ``each(i, cell)``
    is called with every grid cell once it is checked, ``i`` counting from 1 (progress).

    Raises:
        SpecError: unknown profile, unknown field, a value the config rejects, or a metric the trainer
            does not report; the message names the field.
    """
    sets = dict(sets or {})
    prof = resolve_profile(spec, profile, load_profiles() if shared is None else shared)
    for key in sets:
        if error := field_error(f"--set {key}", key):
            raise SpecError(error)
        if key in spec.grid or key in spec.search.space or any(key in c.set for c in spec.cells):
            raise SpecError(f"--set {key}: this spec sweeps it; change the spec's grid, cells or space instead")
    spec, fixed = _shared_values(spec, profile, prof, sets)
    rows = spec.paper.rows if spec.paper else []
    cells: list[Cell] = []
    names: set[str] = set()
    labels: set[int] = set()  # their hashes: 10⁶ labels themselves would hold ~150 MB
    count, compared = 0, False
    if not spec.search.sampled:
        for name, values in _cell_values(spec):
            for seed in spec.seed_values:
                overrides = {**fixed, **values, "train.seed": seed, **sets}
                config = _build(overrides, f"cell {name}")
                paper = next((r for r in rows if _matches(r, config)), None)
                cell = Cell(name, trial_label(name, seed), values, seed, config,
                            paper.label if paper else None, dict(paper.values) if paper else {})
                if hash(cell.label) in labels:
                    raise SpecError(
                        f"cells: two cells share the name {cell.label!r}; give explicit cells distinct labels"
                    )
                labels.add(hash(cell.label))
                names |= _metric_names(config)
                compared = compared or name == spec.compare_to
                count += 1
                if keep is None or len(cells) < keep:
                    cells.append(cell)
                if each is not None:
                    each(count, cell)
    else:
        for key, param in spec.search.space.items():
            for probe in param.probes():
                names |= _metric_names(_build({**fixed, key: probe, "train.seed": spec.seed_values[0], **sets},
                                              f"search.space.{key}={probe!r}"))
    if spec.compare_to is not None and not compared:
        known = ", ".join(dict.fromkeys(c.name for c in cells))
        raise SpecError(f"compare_to: {spec.compare_to!r} is not a cell of this spec; cells: {known}")
    return SweepPlan(spec, prof, fixed, sets, tuple(cells), _check_metric(spec, names), None if keep is None else count)
