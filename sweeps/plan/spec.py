"""Sweep spec schema: the pydantic models of a spec file (``sweeps/*.yaml``).

A spec describes one ablation: fixed ``base`` overrides, a cartesian ``grid`` and/or explicit
``cells`` of dotted :mod:`cdm.config` fields (``exclude`` drops combinations), ``seeds``, a
``search`` (the grid itself, or Optuna over a typed ``space``), the ``metric`` reported and
optimised, an optional ASHA ``scheduler``, ``resources``, ``failure`` handling, the ``paper``'s
numbers per cell, and per-spec patches of the shared profiles (:mod:`sweeps.plan.profiles`).

This module only reads and validates files; :mod:`sweeps.plan.trials` expands a spec into trials and
:mod:`sweeps.plan.resources` sizes them onto a Ray cluster.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, TypeAdapter, ValidationError, field_validator, model_validator

from cdm.config import PaperDataSet, format_validation_error
from cdm.io.yaml import read_mapping
from cdm.metric_names import F1
from sweeps.plan.profiles import Profile, Resources
from sweeps.plan.schema_base import OWNED_FIELDS, SpecError, Strict, field_error
from sweeps.plan.search import SEARCHES, search_kind

__all__ = [
    "DatasetRun",
    "ExplicitCell",
    "Failure",
    "Metric",
    "Paper",
    "PaperRow",
    "Scheduler",
    "Search",
    "SequentialSeeds",
    "Settle",
    "SpaceParam",
    "Spec",
    "load_spec",
]


class PaperRow(Strict):
    """The paper's numbers for the cells whose resolved config matches every ``when`` entry."""

    label: str
    when: dict[str, Any]
    values: dict[str, float]
    """Metric name (as the trainer reports it, e.g. ``eval/f1``, ``eval/cd/teddybear``) → paper value."""


class Paper(Strict):
    table: str
    note: str = ""
    rows: list[PaperRow] = []


class SpaceParam(Strict):
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


class Search(Strict):
    """How trials are chosen: ``kind`` names a registered algorithm (:data:`sweeps.plan.search.SEARCHES`)."""

    kind: str = "grid"
    sampler: Literal["tpe", "random"] = "tpe"
    """Optuna's sampler (``kind: optuna``)."""
    num_samples: int = Field(8, ge=1)
    seed: int = 0
    space: dict[str, SpaceParam] = {}

    @field_validator("kind")
    @classmethod
    def _known(cls, kind: str) -> str:
        search_kind(kind)
        return kind

    @property
    def sampled(self) -> bool:
        """True when the kind draws trials from ``space`` (e.g. Optuna), False for the grid's cells."""
        return search_kind(self.kind).samples_space

    @model_validator(mode="after")
    def _check(self) -> Search:
        if self.sampled and not self.space:
            raise ValueError(f"search.space: search.kind {self.kind} samples it; give at least one dimension")
        if not self.sampled and self.space:
            samplers = ", ".join(name for name, kind in SEARCHES.items() if kind.samples_space)
            raise ValueError(f"search.space: only used by a search that samples it ({samplers})")
        return self


class Metric(Strict):
    name: str = F1.key
    mode: Literal["min", "max"] = "max"


class Scheduler(Strict):
    """``asha`` stops weak trials at rungs of ``grace_evals`` evaluation intervals: ``eval_every`` steps, or with a
    budget in compute (``budget.compute_s``) ``eval_every_s`` seconds of it (time axis: the budget's unit)."""

    kind: Literal["none", "asha"] = "none"
    grace_evals: int = Field(1, ge=1)
    reduction_factor: float = Field(2.0, gt=1.0)

    def stops(self, total: float, every: float) -> list[float]:
        """The points before the last (``total``, in steps or seconds of compute) at which ASHA may stop a trial
        evaluated every ``every`` of that unit: none for ``kind: none``.

        Ray's one-bracket ASHA (``ray/tune/schedulers/async_hyperband.py``, ``_Bracket``) has rungs at
        ``grace × rf^k`` (``grace = grace_evals × every``, k = 0 … ⌊log_rf(total / grace)⌋) and judges a
        trial at the first result it reports at or past a rung: the trainer reports at every evaluation
        (each ``every``) and at the end. A rung whose report is the end stops nothing."""
        grace = self.grace_evals * every
        if self.kind == "none" or grace >= total:
            return []
        rungs, rung = [], grace
        while rung <= total:
            rungs.append(rung)
            rung *= self.reduction_factor
        judged = sorted({min(total, math.ceil(r / every - 1e-9) * every) for r in rungs})
        return [s for s in judged if s < total]


class Failure(Strict):
    max_retries: int = Field(0, ge=0)
    """Restarts of a failed trial (Tune) and of its crashed workers (Train) from the last checkpoint."""


class ExplicitCell(Strict):
    label: str
    set: dict[str, Any] = {}


class DatasetRun(Strict):
    """How the paper ran a spec's table on one data set; used by ``--profile paper`` once ``--set
    data.root=...`` names where that data set is (``--set data.kind=...`` picks one of several)."""

    overrides: dict[str, Any] = {}
    """Dotted config fields the paper used on this data set (e.g. ``priors.render_kind: planar``)."""
    grid: dict[str, list[Any]] = {}
    """Grid axes replaced or added on this data set (e.g. Table 2's ShapeNet categories, with car; Table 4's
    one model per Co3D class)."""


class SequentialSeeds(Strict):
    """``seeds: {min: 2, max: 5, until: settled}``: seeds ``0, 1, …, max − 1`` run in rounds until each
    cell's comparison with its reference settles (:mod:`sweeps.execute.settle`, :mod:`sweeps.compare.sequential`).

    Round 1 trains every cell at ``min`` seeds; after each round a cell whose interval against the
    reference still holds 0 (and is not inside ``settle.margin``) gets one more seed, the reference
    with it, until ``max`` seeds or the command line's ``--budget`` ends. One seed settles nothing
    (its interval covers the held-out objects only), so ``min: 1`` only saves a round when a cell
    fails outright.
    """

    min: int = Field(ge=1)
    """Seeds every cell trains in round 1."""
    max: int = Field(ge=1)
    """Most seeds a cell trains; the planned looks are ``max − min + 1``."""
    until: Literal["settled"]

    @model_validator(mode="after")
    def _check(self) -> SequentialSeeds:
        if self.min > self.max:
            raise ValueError(f"min ({self.min}) must be ≤ max ({self.max})")
        return self

    @property
    def values(self) -> list[int]:
        """The training seeds in the order they run: ``0 … max − 1``."""
        return list(range(self.max))

    @property
    def looks(self) -> int:
        """Planned looks (rounds that can settle a comparison): ``max − min + 1``."""
        return self.max - self.min + 1


UNTIL_SETTLED = SequentialSeeds(min=2, max=5, until="settled")
"""What ``--until-settled`` makes of a spec's list of seeds (a longer list raises ``max`` to its length):
two seeds, the fewest whose interval covers seed variance, up to five, where a comparison still open
is unlikely to settle within a sweep's budget."""


class Settle(Strict):
    margin: float | None = Field(None, gt=0)
    """Equivalence margin in the metric's units: a cell whose interval against the reference lies inside
    ±margin is settled as ``level`` (a TOST-style verdict); null = only better/worse settle."""


class Spec(Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    description: str = ""
    paper: Paper | None = None
    base: dict[str, Any] = {}
    grid: dict[str, list[Any]] = {}
    cells: list[ExplicitCell] = []
    exclude: list[dict[str, Any]] = []
    seeds: list[int] | SequentialSeeds = [0]
    """Training seeds: a list (every cell at each), or ``{min, max, until: settled}`` (:class:`SequentialSeeds`)."""
    settle: Settle = Settle()
    search: Search = Search()
    metric: Metric = Metric()
    scheduler: Scheduler = Scheduler()
    resources: Resources = Resources()
    failure: Failure = Failure()
    profiles: dict[str, Profile] = {}
    compare_to: str | None = None
    """Cell every other cell is paired with in the results table (default: the first cell)."""
    datasets: dict[PaperDataSet, DatasetRun] = {}
    """The data sets the paper ran this table on; empty = the paper's ShapeNet and Co3D alike."""
    stand_in: str = ""
    """What the procedural data set stands in with for the paper's data (shown on the protocol card)."""

    @field_validator("seeds", mode="before")
    @classmethod
    def _one_form(cls, value: Any) -> list[int] | SequentialSeeds:
        # Validated here so an error speaks of the form given, not of both forms of the union.
        try:
            if isinstance(value, dict):
                return SequentialSeeds.model_validate(value)
            if isinstance(value, list):
                return TypeAdapter(list[int]).validate_python(value)
        except ValidationError as exc:
            raise ValueError(format_validation_error(exc, SequentialSeeds)) from None
        if isinstance(value, SequentialSeeds):
            return value
        raise ValueError("Input should be a valid list of seeds, or {min: 2, max: 5, until: settled}")

    @model_validator(mode="after")
    def _check(self) -> Spec:
        dotted = [("base", k) for k in self.base] + [("grid", k) for k in self.grid]
        dotted += [(f"cells[{i}].set", k) for i, c in enumerate(self.cells) for k in c.set]
        dotted += [("search.space", k) for k in self.search.space]
        dotted += [(f"profiles.{p}.overrides", k) for p, prof in self.profiles.items() for k in prof.overrides]
        dotted += [
            (f"paper.rows[{i}].when", k) for i, r in enumerate(self.paper.rows if self.paper else []) for k in r.when
        ]
        dotted += [(f"datasets.{d}.{part}", k) for d, run in self.datasets.items() for part in ("overrides", "grid")
                   for k in getattr(run, part)]
        for where, key in dotted:
            error = field_error(f"{where}.{key}", key)
            # The paper's rows only match cells, so they may name the fields the spec sets itself.
            if error and not (where.startswith("paper") and key in OWNED_FIELDS):
                raise ValueError(error)
        if isinstance(self.seeds, list) and not self.seeds:
            raise ValueError("seeds: empty list; give at least one seed")
        if isinstance(self.seeds, list) and len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds: repeated values in {self.seeds}")
        for key, values in self.grid.items():
            if not values:
                raise ValueError(f"grid.{key}: empty list; give at least one value")
        if not self.search.sampled and not self.grid and not self.cells:
            raise ValueError("grid: empty; give at least one dotted config field with a list of values (or cells)")
        if self.search.sampled and (self.grid or self.cells or len(self.seed_values) > 1):
            raise ValueError(
                f"search: {self.search.kind} explores search.space; leave grid and cells empty and give one seed"
            )
        if self.sequential is not None and self.scheduler.kind != "none":
            raise ValueError("scheduler: seeds until settled compares finished trials; a scheduler stopping some early "
                             "would compare unequal training: use kind none")
        for i, rule in enumerate(self.exclude):
            for key, value in rule.items():
                if key not in self.grid or value not in self.grid[key]:
                    raise ValueError(f"exclude[{i}].{key}: {value!r} is not a value of grid.{key}")
        return self

    @property
    def sequential(self) -> SequentialSeeds | None:
        """The rule of a sweep whose seeds run until settled; None for a fixed list of seeds."""
        return self.seeds if isinstance(self.seeds, SequentialSeeds) else None

    @property
    def seed_values(self) -> list[int]:
        """Every training seed a cell may run, in order (a sequential sweep's up to ``max``)."""
        return self.seeds.values if isinstance(self.seeds, SequentialSeeds) else list(self.seeds)

    def until_settled(self) -> Spec:
        """This spec with ``--until-settled``: a list of seeds becomes :data:`UNTIL_SETTLED` (``max`` at least
        the list's length); a sequential spec stays as it is.

        Raises:
            SpecError: an Optuna spec (it samples one trial per point, with no cell to settle).
        """
        if self.search.sampled:
            raise SpecError(f"--until-settled: search.kind {self.search.kind} samples one trial per point; seeds until "
                            "settled need a grid of cells")
        if self.sequential is not None:
            return self
        rule = UNTIL_SETTLED.model_copy(update={"max": max(UNTIL_SETTLED.max, len(self.seed_values))})
        try:
            return Spec.model_validate({**self.model_dump(exclude_unset=True), "seeds": rule.model_dump()})
        except ValidationError as exc:
            raise SpecError(f"--until-settled: {format_validation_error(exc, Spec)}") from None


def load_spec(path: str | Path) -> Spec:
    """Read and validate a spec file; :class:`SpecError` names the first bad field."""
    path = Path(path)
    try:
        return Spec.model_validate(read_mapping(path, "spec"))
    except ValidationError as exc:
        raise SpecError(f"{path}: {format_validation_error(exc, Spec)}") from None
    except ValueError as exc:  # the file: over a cap of cdm.io.yaml, not YAML, not a mapping
        raise SpecError(str(exc)) from None

