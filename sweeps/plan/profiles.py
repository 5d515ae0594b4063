"""The shared profiles' schema: ``sweeps/profiles.yaml`` (``smoke``, ``local``, ``paper``; a profile holds
sizes, the ``budget`` and resources), a profile's ``recipe`` read from a cdm config file.

A spec's ``profiles:`` section patches these (:class:`sweeps.plan.spec.Spec`); :mod:`sweeps.plan.trials`
resolves the two into one profile per run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, model_validator

from cdm.config import ConfigError, PaperDataSet, format_validation_error, load_config, read_config_file
from cdm.io.yaml import read_mapping
from sweeps.plan.schema_base import KNOWN_FIELDS, SpecError, Strict, field_error

__all__ = ["PROFILES_FILE", "RUN_ONLY", "Budget", "Profile", "Resources", "SharedProfile", "load_profiles"]

PROFILES_FILE = Path(__file__).resolve().parents[1] / "profiles.yaml"
"""Shared profiles every spec inherits; a spec's ``profiles:`` section patches them."""


class Resources(Strict):
    """Per trial: ``workers_per_trial`` Ray Train workers (0 = Train's local mode in the trial's own process)."""

    workers_per_trial: int = Field(0, ge=0)
    cpus_per_worker: float = Field(1.0, gt=0)
    gpus_per_worker: float = Field(0.0, ge=0)
    max_concurrent_trials: int | None = Field(None, ge=1)
    """Cap on concurrent trials; null = as many as the cluster's CPUs/GPUs fit."""


class Budget(Strict):
    """A profile's training length; a field left out keeps its default in :class:`cdm.config.TrainConfig`,
    the paper's (PC²'s ``max_steps``), which is that value's one home."""

    steps: int | None = Field(None, ge=1)
    """Training steps; with ``compute_s``, the most a trial may take (and the cosine decay's length)."""
    eval_every: int | None = Field(None, ge=1)
    compute_s: float | None = Field(None, gt=0)
    """Seconds of compute per trial (``train.compute_budget_s``: CPU seconds of the trial's process here, GPU
    wall seconds on CUDA, evaluation not counted): trials of different step cost train for the same compute,
    and ASHA's rungs count in these seconds; null = a budget in steps."""
    eval_every_s: float | None = Field(None, gt=0)
    """With ``compute_s``: evaluate each time a trial's compute passes a multiple of this (ASHA's rung unit)."""

    @model_validator(mode="after")
    def _check(self) -> Budget:
        if self.eval_every_s is not None and self.compute_s is None:
            raise ValueError("budget.eval_every_s: only with budget.compute_s (a budget in seconds of compute)")
        return self


class Profile(Strict):
    """A named override set; in a spec every part is a patch of the shared profile of that name."""

    description: str = ""
    budget: Budget = Budget()
    overrides: dict[str, Any] = {}
    resources: Resources = Resources()
    num_samples: int | None = Field(None, ge=1)
    """Optuna trials in this profile (overrides ``search.num_samples``)."""
    datasets: dict[PaperDataSet, dict[str, Any]] = {}
    """Dotted config fields this profile sets when a run reads that data set (``data.kind``), after its
    ``overrides``: the paper profile's home for each reference's data protocol (BDM on ShapeNet, PC² on Co3D)."""


class SharedProfile(Profile):
    """A profile of ``sweeps/profiles.yaml``, which may start from a cdm config file."""

    recipe: str | None = None
    """A cdm config file (``configs/quick.yaml``; relative to ``profiles.yaml``) whose fields are this
    profile's first overrides, so a single run and the sweeps share one recipe; ``overrides`` then says where
    the sweeps differ. Its :data:`RUN_ONLY` fields are the single run's and stay out."""


RUN_ONLY = ("train.steps", "train.eval_every", "train.compute_budget_s", "train.eval_every_s", "train.threads",
            "train.out_dir")
"""A recipe's fields that a sweep sets per trial instead: the profile's budget and CPUs, the trial's folder."""


def _recipe(path: Path) -> dict[str, Any]:
    """The fields a recipe file writes, dotted, minus :data:`RUN_ONLY`; the file validated as a config."""
    try:
        tree = read_config_file(path)
        load_config(tree)
    except ConfigError as exc:
        raise SpecError(f"recipe {path}: {exc}") from None
    out, todo = {}, [("", tree)]
    while todo:
        prefix, tree = todo.pop(0)
        for key, value in tree.items():
            if isinstance(value, dict) and f"{prefix}{key}" not in KNOWN_FIELDS:
                todo.append((f"{prefix}{key}.", value))
            elif f"{prefix}{key}" not in RUN_ONLY:
                out[f"{prefix}{key}"] = value
    return out


def load_profiles(path: str | Path = PROFILES_FILE) -> dict[str, Profile]:
    """The shared profiles, a recipe's fields first in its overrides, each field checked: known, and not one
    another section sets."""
    path = Path(path)
    try:
        profiles = {name: SharedProfile.model_validate(body) for name, body in read_mapping(path, "profiles").items()}
    except ValidationError as exc:
        raise SpecError(f"{path}: {format_validation_error(exc, SharedProfile)}") from None
    except ValueError as exc:  # the file: over a cap of cdm.io.yaml, not YAML, not a mapping
        raise SpecError(str(exc)) from None
    for name, prof in profiles.items():
        if prof.recipe is not None:
            profiles[name] = prof = prof.model_copy(
                update={"overrides": {**_recipe(path.parent / prof.recipe), **prof.overrides}})
        keys = [(f"overrides.{k}", k) for k in prof.overrides]
        keys += [(f"datasets.{d}.{k}", k) for d, fields in prof.datasets.items() for k in fields]
        for where, key in keys:
            if error := field_error(f"{path}: {name}.{where}", key):
                raise SpecError(error)
    return profiles
