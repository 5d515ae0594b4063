"""What every sweep file's schema shares: the strict model, :class:`SpecError` and which dotted
:mod:`cdm.config` fields a file may set.

:mod:`sweeps.plan.spec` (a spec file) and :mod:`sweeps.plan.profiles` (the shared profiles) build on it.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from cdm.config import config_field_paths

__all__ = ["KNOWN_FIELDS", "OWNED_FIELDS", "SpecError", "Strict", "field_error"]

KNOWN_FIELDS = frozenset(config_field_paths())
"""Every dotted config field (``python -m cdm fields``)."""

# Fields a spec sets through its own sections, so each has one home.
OWNED_FIELDS = {
    "train.steps": "the profile's budget.steps",
    "train.eval_every": "the profile's budget.eval_every",
    "train.compute_budget_s": "the profile's budget.compute_s",
    "train.eval_every_s": "the profile's budget.eval_every_s",
    "train.seed": "the spec's seeds",
}


class SpecError(ValueError):
    """A sweep spec, profile or ``--set`` value is invalid; the message names the field."""


def field_error(where: str, key: str) -> str | None:
    """Why the dotted config field ``key`` cannot be set at ``where`` (unknown, or set by another
    section: :data:`OWNED_FIELDS`), as ``<where>: <reason>``; None when it can."""
    if key not in KNOWN_FIELDS:
        return f"{where}: unknown config field (see `python -m cdm fields`)"
    if key in OWNED_FIELDS:
        return f"{where}: set it through {OWNED_FIELDS[key]} instead"
    return None


class Strict(BaseModel):
    """A sweep file's model: an unknown key is a typo, not a field to ignore."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
