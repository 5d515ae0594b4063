"""``--budget`` of a sequential sweep: a wall time or a number of trials, parsed to one line on any text.

Every form is capped: ``str.isdigit`` accepts ``²``, which ``int`` refuses; ``int`` refuses 5,001 digits;
a 401-digit number of seconds is infinite as a float. Here only ASCII digits of bounded length reach a
conversion, and the value must lie within :data:`MAX_BUDGET_TRIALS` or :data:`MAX_BUDGET_SECONDS`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from sweeps.plan.limits import LimitError
from sweeps.plan.schema_base import SpecError
from sweeps.plan.trials import SweepPlan

__all__ = ["MAX_BUDGET_SECONDS", "MAX_BUDGET_TRIALS", "SeedBudget", "check_budget", "parse_budget"]


@dataclass(frozen=True)
class SeedBudget:
    """``--budget``: the wall time after which no new seed starts, or the most trials a sequential sweep runs."""

    seconds: float | None = None
    trials: int | None = None

    def text(self) -> str:
        if self.trials is not None:
            return f"{self.trials} trials"
        return f"{self.seconds / 60:g} min wall time"


MAX_BUDGET_TRIALS = 100_000
"""Most trials ``--budget N`` may name (a hundred times the default trial cap, :mod:`sweeps.plan.limits`)."""
MAX_BUDGET_SECONDS = 366 * 86_400
"""Longest wall time ``--budget`` may name: a year."""
_TRIALS = re.compile(r"[0-9]{1,9}")
_DURATION = re.compile(r"([0-9]{1,9}(?:\.[0-9]{1,6})?)([hms])")
"""ASCII digits only (``str.isdigit`` takes ``²``, which ``int`` refuses), few enough to stay finite."""


def parse_budget(text: str) -> SeedBudget:
    """``2h``, ``45m``, ``30s`` (wall time, at most :data:`MAX_BUDGET_SECONDS`) or ``12`` (trials, 1 to
    :data:`MAX_BUDGET_TRIALS`) as a :class:`SeedBudget`.

    Raises:
        LimitError: anything else (empty, ``²``, 5,001 digits, ``1e400`` seconds), naming ``--budget`` and the
            accepted forms.
    """
    if not isinstance(text, str):
        raise LimitError(f"--budget {str(text)[:40]!r}: expected text such as 2h or 12")
    text = text.strip()
    if _TRIALS.fullmatch(text) and 1 <= int(text) <= MAX_BUDGET_TRIALS:
        return SeedBudget(trials=int(text))
    if (match := _DURATION.fullmatch(text)) and 0 < (
        seconds := float(match[1]) * {"h": 3600, "m": 60, "s": 1}[match[2]]
    ) <= MAX_BUDGET_SECONDS:
        return SeedBudget(seconds=seconds)
    shown = repr(text[:40]) + ("…" if len(text) > 40 else "")
    raise LimitError(
        f"--budget {shown}: give a wall time (2h, 45m, 30s; at most {MAX_BUDGET_SECONDS // 86_400} days) or a "
        f"number of trials (1 to {MAX_BUDGET_TRIALS})"
    )


def check_budget(plan: SweepPlan, budget: SeedBudget | None) -> None:
    """Refuse a ``--budget`` the plan cannot spend: without seeds until settled, or a trial count below round 1's.

    Raises:
        SpecError: naming ``--budget`` and the fix.
    """
    if budget is None:
        return
    if plan.sequential is None:
        raise SpecError("--budget: only seeds run until settled spend a budget; add --until-settled "
                        "(or give the spec seeds: {min: 2, max: 5, until: settled})")
    first = len(plan.first_round)
    if budget.trials is not None and budget.trials < first:
        raise SpecError(f"--budget {budget.trials}: round 1 alone runs {first} trials (every cell at "
                        f"{plan.sequential.min} seeds); give at least {first}")
