"""Sweep specs: schema, profiles, and expansion into validated trial cells — before Ray starts.

A spec (``sweeps/*.yaml``) describes one ablation: fixed ``base`` overrides, a cartesian ``grid``
and/or explicit ``cells`` of dotted :mod:`cdm.config` fields (``exclude`` drops combinations),
``seeds``, a ``search`` (the grid itself, or Optuna over a typed ``space``), the ``metric`` reported
and optimised, an optional ASHA ``scheduler``, ``resources``, ``failure`` handling, the ``paper``'s
numbers per cell, and per-spec patches of the shared profiles in ``sweeps/profiles.yaml``
(``smoke``, ``local``, ``paper``; a profile holds sizes, the ``budget`` and resources).

One trial's config is resolved in this order, later wins::

    cdm defaults < shared profile overrides < spec base < spec profile overrides
      < budget (train.steps, train.eval_every) and train.threads (= CPUs per worker)
      < cell values < seed (train.seed) < --set

:func:`expand` builds the :class:`cdm.config.Config` of every cell (and checks the metric against
:func:`cdm.train.metric_names`), so a typo fails with one :class:`SpecError` naming the field.
"""

from __future__ import annotations

import itertools
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cdm.config import Config, ConfigError, config_field_paths, load_config
from sweeps.limits import LimitError, load_yaml

__all__ = [
    "PROFILES_FILE",
    "Cell",
    "Concurrency",
    "ResolvedProfile",
    "Spec",
    "SpecError",
    "SweepPlan",
    "cell_name",
    "expand",
    "load_profiles",
    "load_spec",
    "plan_concurrency",
]

PROFILES_FILE = Path(__file__).with_name("profiles.yaml")
"""Shared profiles every spec inherits; a spec's ``profiles:`` section patches them."""

# Fields a spec sets through its own sections, so each has one home.
_OWNED = {
    "train.steps": "the profile's budget.steps",
    "train.eval_every": "the profile's budget.eval_every",
    "train.seed": "the spec's seeds",
}

# Paper notation for readable cell names; other fields use their last dotted part.
_SHORT_NAMES = {"priors.num_views": "H", "priors.lambda_3d": "λ", "data.categories": "categories"}


class SpecError(ValueError):
    """A sweep spec, profile or ``--set`` value is invalid; the message names the field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class PaperRow(_Strict):
    """The paper's numbers for the cells whose resolved config matches every ``when`` entry."""

    label: str
    when: dict[str, Any]
    values: dict[str, float]
    """Metric name (as the trainer reports it, e.g. ``eval/f1``, ``eval/cd/teddybear``) → paper value."""


class Paper(_Strict):
    table: str
    note: str = ""
    rows: list[PaperRow] = []


class SpaceParam(_Strict):
    """One Optuna dimension: ``float``/``log_float``/``int`` in [low, high], or ``categorical`` choices."""

    type: Literal["float", "log_float", "int", "categorical"]
    low: float | None = None
    high: float | None = None
    step: float | None = Field(None, gt=0)
    choices: list[Any] | None = None

    @model_validator(mode="after")
    def _check(self) -> SpaceParam:
        if self.type == "categorical":
            if not self.choices:
                raise ValueError("categorical needs a non-empty choices list")
            if self.low is not None or self.high is not None:
                raise ValueError("categorical takes choices, not low/high")
            return self
        if self.low is None or self.high is None or self.choices is not None:
            raise ValueError(f"{self.type} needs low and high (and no choices)")
        if self.low >= self.high:
            raise ValueError(f"low ({self.low}) must be < high ({self.high})")
        if self.type == "log_float" and self.low <= 0:
            raise ValueError(f"log_float needs low > 0 (got {self.low})")
        if self.type == "log_float" and self.step is not None:
            raise ValueError("log_float takes no step (Optuna cannot step a log scale); use float with a step")
        if self.type == "int" and (self.low != int(self.low) or self.high != int(self.high)):
            raise ValueError("int needs whole-number low and high")
        return self

    def probes(self) -> list[Any]:
        """Values that bound this dimension, used to validate the config before the search runs."""
        if self.type == "categorical":
            return list(self.choices or [])
        cast = int if self.type == "int" else float
        return [cast(self.low), cast(self.high)]


class Search(_Strict):
    kind: Literal["grid", "optuna"] = "grid"
    sampler: Literal["tpe", "random"] = "tpe"
    num_samples: int = Field(8, ge=1)
    seed: int = 0
    space: dict[str, SpaceParam] = {}

    @model_validator(mode="after")
    def _check(self) -> Search:
        if self.kind == "optuna" and not self.space:
            raise ValueError("search.space: optuna needs at least one dimension")
        if self.kind == "grid" and self.space:
            raise ValueError("search.space: only used with search.kind optuna")
        return self


class Metric(_Strict):
    name: str = "eval/f1"
    mode: Literal["min", "max"] = "max"


class Scheduler(_Strict):
    """``asha`` stops weak trials at rungs of ``grace_evals`` × eval_every steps (time axis: train step)."""

    kind: Literal["none", "asha"] = "none"
    grace_evals: int = Field(1, ge=1)
    reduction_factor: float = Field(2.0, gt=1.0)


class Resources(_Strict):
    """Per trial: ``workers_per_trial`` Ray Train workers (0 = Train's local mode in the trial's own process)."""

    workers_per_trial: int = Field(0, ge=0)
    cpus_per_worker: float = Field(1.0, gt=0)
    gpus_per_worker: float = Field(0.0, ge=0)
    max_concurrent_trials: int | None = Field(None, ge=1)
    """Cap on concurrent trials; null = as many as the cluster's CPUs/GPUs fit."""


class Failure(_Strict):
    max_retries: int = Field(0, ge=0)
    """Restarts of a failed trial (Tune) and of its crashed workers (Train) from the last checkpoint."""


class Budget(_Strict):
    steps: int | None = Field(None, ge=1)
    eval_every: int | None = Field(None, ge=1)


class Profile(_Strict):
    """A named override set; in a spec every part is a patch of the shared profile of that name."""

    description: str = ""
    budget: Budget = Budget()
    overrides: dict[str, Any] = {}
    resources: Resources = Resources()
    num_samples: int | None = Field(None, ge=1)
    """Optuna trials in this profile (overrides ``search.num_samples``)."""


class ExplicitCell(_Strict):
    label: str
    set: dict[str, Any] = {}


class DatasetRun(_Strict):
    """How the paper ran a spec's table on one data set; used by ``--profile paper`` once ``--set
    data.root=...`` names where that data set is (``--set data.kind=...`` picks one of several)."""

    overrides: dict[str, Any] = {}
    """Dotted config fields the paper used on this data set (e.g. ``priors.render_kind: planar``)."""
    grid: dict[str, list[Any]] = {}
    """Grid axes replaced on this data set (e.g. Table 2's ShapeNet categories, with car)."""


class Spec(_Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    description: str = ""
    paper: Paper | None = None
    base: dict[str, Any] = {}
    grid: dict[str, list[Any]] = {}
    cells: list[ExplicitCell] = []
    exclude: list[dict[str, Any]] = []
    seeds: list[int] = Field([0], min_length=1)
    search: Search = Search()
    metric: Metric = Metric()
    scheduler: Scheduler = Scheduler()
    resources: Resources = Resources()
    failure: Failure = Failure()
    profiles: dict[str, Profile] = {}
    compare_to: str | None = None
    """Cell every other cell is paired with in the results table (default: the first cell)."""
    datasets: dict[Literal["shapenet_r2n2", "co3d"], DatasetRun] = {}
    """The data sets the paper ran this table on; empty = the paper's ShapeNet and Co3D alike."""
    stand_in: str = ""
    """What the procedural data set stands in with for the paper's data (shown on the protocol card)."""

    @model_validator(mode="after")
    def _check(self) -> Spec:
        known = set(config_field_paths())
        dotted = [("base", k) for k in self.base] + [("grid", k) for k in self.grid]
        dotted += [(f"cells[{i}].set", k) for i, c in enumerate(self.cells) for k in c.set]
        dotted += [("search.space", k) for k in self.search.space]
        dotted += [(f"profiles.{p}.overrides", k) for p, prof in self.profiles.items() for k in prof.overrides]
        dotted += [(f"paper.rows[{i}].when", k) for i, r in enumerate(self.paper.rows if self.paper else []) for k in r.when]
        dotted += [(f"datasets.{d}.{part}", k) for d, run in self.datasets.items() for part in ("overrides", "grid")
                   for k in getattr(run, part)]
        for where, key in dotted:
            if key not in known:
                raise ValueError(f"{where}.{key}: unknown config field (see `python -m cdm fields`)")
            if key in _OWNED and not where.startswith("paper"):
                raise ValueError(f"{where}.{key}: set it through {_OWNED[key]} instead")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds: repeated values in {self.seeds}")
        for key, values in self.grid.items():
            if not values:
                raise ValueError(f"grid.{key}: empty list; give at least one value")
        if self.search.kind == "grid" and not self.grid and not self.cells:
            raise ValueError("grid: empty; give at least one dotted config field with a list of values (or cells)")
        if self.search.kind == "optuna" and (self.grid or self.cells or len(self.seeds) > 1):
            raise ValueError("search: optuna explores search.space; leave grid and cells empty and give one seed")
        for d, run in self.datasets.items():
            if set(run.grid) - set(self.grid):
                raise ValueError(f"datasets.{d}.grid: {sorted(set(run.grid) - set(self.grid))} are not axes of grid")
        for i, rule in enumerate(self.exclude):
            for key, value in rule.items():
                if key not in self.grid or value not in self.grid[key]:
                    raise ValueError(f"exclude[{i}].{key}: {value!r} is not a value of grid.{key}")
        return self


@dataclass(frozen=True)
class ResolvedProfile:
    name: str
    description: str
    steps: int
    eval_every: int
    overrides: dict[str, Any]
    resources: Resources
    num_samples: int | None


@dataclass(frozen=True)
class Cell:
    """One trial of a grid sweep: a cell of the grid at one seed."""

    name: str
    """Readable cell name without the seed, e.g. ``point_size=0.04`` (an explicit cell's label)."""
    label: str
    """Unique trial label, ``<name> · seed <seed>``; names the MLflow child run."""
    values: dict[str, Any]
    seed: int
    overrides: dict[str, Any]
    """Every dotted override of this trial; ``load_config(None, overrides)`` rebuilds its config."""
    config: Config
    paper_label: str | None = None
    paper: dict[str, float] = field(default_factory=dict)


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

    @property
    def num_trials(self) -> int:
        if self.spec.search.kind == "optuna":
            return self.profile.num_samples or self.spec.search.num_samples
        return len(self.cells)

    def trial(self, tune_config: dict[str, Any]) -> Cell:
        """The trial a Tune config stands for: ``{"cell": label}`` (grid) or sampled values (Optuna)."""
        if self.spec.search.kind == "grid":
            return next(c for c in self.cells if c.label == tune_config["cell"])
        values = {k: tune_config[k] for k in self.spec.search.space}
        seed = self.spec.seeds[0]
        overrides = {**self.fixed, **values, "train.seed": seed, **self.sets}
        name = cell_name(values)
        return Cell(name, f"{name} · seed {seed}", values, seed, overrides, load_config(None, overrides))


@dataclass(frozen=True)
class Concurrency:
    """How trials map onto the cluster: what each trial asks for and how many run at once."""

    trial_resources: dict[str, float]
    """What the Tune trial's own actor reserves (it runs the loop itself in local mode)."""
    cpus_per_trial: float
    gpus_per_trial: float
    max_concurrent: int


def _format(err: ValidationError, where: str) -> str:
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            msg = f"unknown key; allowed: {', '.join(_allowed_keys(e['loc'][:-1]))}"
        elif e["type"] == "literal_error":
            msg = f"{msg} (got {e['input']!r})"
        lines.append(f"{loc}: {msg}" if loc else msg)
    return f"{where}: " + "; ".join(lines)


def _model_in(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _allowed_keys(loc: tuple) -> list[str]:
    """Field names of the schema model at ``loc`` (list indices and dict keys are stepped over)."""
    model: type[BaseModel] = Spec
    for part in loc:
        if isinstance(part, str) and part in model.model_fields:
            model = _model_in(model.model_fields[part].annotation) or model
    return list(model.model_fields)


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        tree = load_yaml(path)
    except LimitError as exc:
        raise SpecError(str(exc)) from None
    if not isinstance(tree, dict):
        raise SpecError(f"{path}: top level must be a mapping")
    return tree


def load_spec(path: str | Path) -> Spec:
    """Read and validate a spec file; :class:`SpecError` names the first bad field."""
    path = Path(path)
    try:
        return Spec.model_validate(_read_yaml(path))
    except ValidationError as exc:
        raise SpecError(_format(exc, str(path))) from None


def load_profiles(path: str | Path = PROFILES_FILE) -> dict[str, Profile]:
    """The shared profiles; each must give a full budget."""
    path = Path(path)
    try:
        profiles = {name: Profile.model_validate(body) for name, body in _read_yaml(path).items()}
    except ValidationError as exc:
        raise SpecError(_format(exc, str(path))) from None
    known = set(config_field_paths())
    for name, prof in profiles.items():
        if prof.budget.steps is None or prof.budget.eval_every is None:
            raise SpecError(f"{path}: {name}.budget: give both steps and eval_every")
        for key in prof.overrides:
            if key not in known:
                raise SpecError(f"{path}: {name}.overrides.{key}: unknown config field")
            if key in _OWNED:
                raise SpecError(f"{path}: {name}.overrides.{key}: set it through {_OWNED[key]} instead")
    return profiles


def _patch(model: BaseModel, patch: BaseModel) -> dict[str, Any]:
    return {**model.model_dump(exclude_unset=True), **patch.model_dump(exclude_unset=True)}


def resolve_profile(spec: Spec, name: str, shared: dict[str, Profile]) -> ResolvedProfile:
    if name not in shared and name not in spec.profiles:
        raise SpecError(f"profile {name!r}: unknown; available: {', '.join(sorted({*shared, *spec.profiles}))}")
    base = shared.get(name, Profile())
    local = spec.profiles.get(name, Profile())
    budget = Budget.model_validate(_patch(base.budget, local.budget))
    if budget.steps is None or budget.eval_every is None:
        raise SpecError(f"profiles.{name}.budget: give both steps and eval_every")
    resources = Resources.model_validate({**_patch(base.resources, spec.resources), **local.resources.model_dump(exclude_unset=True)})
    return ResolvedProfile(
        name=name,
        description=local.description or base.description,
        steps=budget.steps,
        eval_every=budget.eval_every,
        overrides={**base.overrides, **spec.base, **local.overrides},
        resources=resources,
        num_samples=local.num_samples or base.num_samples,
    )


def _fmt_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "+".join(str(v) for v in value) or "all"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def cell_name(values: dict[str, Any]) -> str:
    """Readable name of swept ``values``: ``point_size=0.04 · H=10`` (paper notation where it has one)."""
    return " · ".join(f"{_SHORT_NAMES.get(k, k.split('.')[-1])}={_fmt_value(v)}" for k, v in values.items())


def _cell_values(spec: Spec) -> list[tuple[str, dict[str, Any]]]:
    """(name, swept values) per cell: explicit cells crossed with the grid, minus excluded combinations."""
    keys = list(spec.grid)
    combos = [dict(zip(keys, vals)) for vals in itertools.product(*spec.grid.values())]
    combos = [c for c in combos if not any(all(c[k] == v for k, v in rule.items()) for rule in spec.exclude)]
    explicit = spec.cells or [ExplicitCell(label="")]
    out = []
    for cell in explicit:
        for combo in combos:
            name = " · ".join(p for p in (cell.label, cell_name(combo)) if p)
            out.append((name, {**cell.set, **combo}))
    return out


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


def _check_metric(spec: Spec, configs: list[Config]) -> tuple[str, ...]:
    from cdm.data import list_categories
    from cdm.train import metric_names

    names: set[str] = set()
    for cfg in configs:
        try:
            names.update(metric_names(cfg, list_categories(cfg)))
        except ValueError as exc:
            raise SpecError(str(exc)) from None
    if spec.metric.name not in names:
        headline = sorted(n for n in names if n.count("/") == 1)
        raise SpecError(f"metric.name: {spec.metric.name!r} is not reported by the trainer; choose one of "
                        f"{', '.join(headline)} or a per-category name like eval/f1/<category>")
    return tuple(sorted(names))


def _dataset_run(spec: Spec, profile: str, sets: dict[str, Any]) -> DatasetRun | None:
    """The paper's run on the data set ``--set data.root`` points at (paper profile only); sets
    ``data.kind`` in ``sets`` when the spec names one data set and ``--set`` gives none."""
    if profile != "paper" or "data.root" not in sets or not spec.datasets:
        return None
    if "data.kind" not in sets:
        if len(spec.datasets) > 1:
            raise SpecError(f"--set data.kind: this table ran on {' and '.join(spec.datasets)}; say which data.root holds")
        sets["data.kind"] = next(iter(spec.datasets))
    return spec.datasets.get(sets["data.kind"])


def expand(
    spec: Spec,
    profile: str = "local",
    sets: dict[str, Any] | None = None,
    shared: dict[str, Profile] | None = None,
) -> SweepPlan:
    """Resolve ``profile`` and ``--set`` values and build every cell's config.

    Raises:
        SpecError: unknown profile, unknown field, a value the config rejects, or a metric the trainer
            does not report; the message names the field.
    """
    sets = dict(sets or {})
    prof = resolve_profile(spec, profile, load_profiles() if shared is None else shared)
    known = set(config_field_paths())
    for key in sets:
        if key not in known:
            raise SpecError(f"--set {key}: unknown config field (see `python -m cdm fields`)")
        if key in _OWNED:
            raise SpecError(f"--set {key}: set it through {_OWNED[key]} (or --profile) instead")
        if key in spec.grid or key in spec.search.space or any(key in c.set for c in spec.cells):
            raise SpecError(f"--set {key}: this spec sweeps it; change the spec's grid, cells or space instead")
    run = _dataset_run(spec, profile, sets)
    if run is not None:
        spec = spec.model_copy(update={"grid": {**spec.grid, **run.grid}})
    fixed = {**prof.overrides, **(run.overrides if run else {}), "train.steps": prof.steps, "train.eval_every": prof.eval_every}
    fixed.setdefault("train.threads", max(1, int(prof.resources.cpus_per_worker)))
    _build({**fixed, **sets}, f"profile {profile}")
    rows = spec.paper.rows if spec.paper else []
    cells: list[Cell] = []
    configs: list[Config] = []
    if spec.search.kind == "grid":
        for name, values in _cell_values(spec):
            for seed in spec.seeds:
                overrides = {**fixed, **values, "train.seed": seed, **sets}
                config = _build(overrides, f"cell {name}")
                paper = next((r for r in rows if _matches(r, config)), None)
                cells.append(Cell(name, f"{name} · seed {seed}", values, seed, overrides, config,
                                  paper.label if paper else None, dict(paper.values) if paper else {}))
                configs.append(config)
    else:
        for key, param in spec.search.space.items():
            for probe in param.probes():
                configs.append(_build({**fixed, key: probe, "train.seed": spec.seeds[0], **sets}, f"search.space.{key}={probe!r}"))
    labels = [c.label for c in cells]
    if len(set(labels)) != len(labels):
        twice = sorted({label for label in labels if labels.count(label) > 1})
        raise SpecError(f"cells: two cells share the name {twice[0]!r}; give explicit cells distinct labels")
    if spec.compare_to is not None and spec.compare_to not in {c.name for c in cells}:
        known = ", ".join(dict.fromkeys(c.name for c in cells))
        raise SpecError(f"compare_to: {spec.compare_to!r} is not a cell of this spec; cells: {known}")
    names = _check_metric(spec, configs)
    return SweepPlan(spec, prof, fixed, sets, tuple(cells), names)


def plan_concurrency(
    resources: Resources, cpus: float, gpus: float, num_trials: int, remote: bool = False
) -> Concurrency:
    """Size concurrency from the cluster so trials never wait on each other for CPUs (no deadlock).

    In local mode (``workers_per_trial == 0``) the trial's actor trains, so it reserves the worker's
    CPUs/GPUs. With real Train workers the trial actor only waits on ``TorchTrainer.fit``; it
    reserves a token CPU and the workers are counted against the cap instead.

    Args:
        cpus, gpus: what the cluster has; with ``remote``, the most it could offer (its nodes, or
            the bounds its autoscaler publishes: :func:`sweeps.trial.cluster_capacity`).
        remote: a cluster joined by address, which may autoscale. Only one trial must fit, and
            concurrency is ``resources.max_concurrent_trials`` or every trial at once: waiting
            trials are the demand that makes the autoscaler add nodes (a GPU cluster often starts
            with none), so sizing from the nodes up at start would pin the sweep to them.

    Raises:
        SpecError: one trial needs more than the whole cluster has (could offer, with ``remote``).
    """
    workers = max(1, resources.workers_per_trial)
    per_cpu = workers * resources.cpus_per_worker
    per_gpu = workers * resources.gpus_per_worker
    if resources.workers_per_trial == 0:
        trial = {"cpu": resources.cpus_per_worker, "gpu": resources.gpus_per_worker}
    else:
        trial = {"cpu": 0.01, "gpu": 0.0}
        per_cpu += trial["cpu"]
    if per_cpu > cpus or per_gpu > gpus:
        has = "could offer at most" if remote else "has"
        raise SpecError(
            f"resources: one trial needs {per_cpu:g} CPUs and {per_gpu:g} GPUs but the cluster {has} {cpus:g} and {gpus:g}; "
            "lower resources.cpus_per_worker / gpus_per_worker / workers_per_trial"
            + ("; or give the cluster a node type that fits one trial (its autoscaler's bounds count, where it "
               "publishes them; otherwise the nodes up now: keep one such node up, e.g. min_workers: 1)" if remote else "")
        )
    if remote:
        return Concurrency(trial, per_cpu, per_gpu, min(resources.max_concurrent_trials or num_trials, num_trials))
    # The small epsilon keeps 2 CPUs / 0.4 at 5, not 4.999… → 4 (Ray itself counts in 1e-4 units).
    fit = int(cpus / per_cpu + 1e-6)
    if per_gpu > 0:
        fit = min(fit, int(gpus / per_gpu + 1e-6))
    cap = resources.max_concurrent_trials or fit
    return Concurrency(trial, per_cpu, per_gpu, max(1, min(fit, cap, num_trials)))
