"""A plan in words, before anything starts: what ``--dry-run`` prints (profile, budget, resources, the
fixed settings, the protocol card and every trial), folded to the terminal's 120 columns."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

from sweeps.plan.protocol import plan_card
from sweeps.plan.resources import plan_concurrency
from sweeps.plan.schema_base import SpecError
from sweeps.plan.search import search_kind
from sweeps.plan.trials import SweepPlan

__all__ = ["describe", "wrapped"]


def describe(plan: SweepPlan, cpus: float | None, gpus: float | None, rule: Sequence[str] = ()) -> str:
    """The dry-run text: profile, search, resource plan and every trial (or a sampled search's space); ``rule``:
    a sequential sweep's lines (its rule, worst case and budget, :meth:`sweeps.execute.settle.UntilSettled.lines`)."""
    spec, prof, r = plan.spec, plan.profile, plan.profile.resources
    out = [
        f"profile {prof.name}: {prof.description}".rstrip(": "),
        f"budget: {prof.budget_text()}",
        f"metric: {spec.metric.name} ({spec.metric.mode}); max retries per trial: {spec.failure.max_retries}",
        f"scored on: {_split(plan)}",
        f"scheduler: {_scheduler(plan)}",
    ]
    mode = (
        "Train local mode (loop inside the trial)"
        if r.workers_per_trial == 0
        else f"{r.workers_per_trial} Train workers"
    )
    line = f"resources: {mode}, {r.cpus_per_worker:g} CPUs + {r.gpus_per_worker:g} GPUs per worker"
    if cpus is None:
        line += "; concurrency derived from the cluster at run time"
    else:
        try:
            conc = plan_concurrency(r, cpus, gpus or 0.0, plan.num_trials)
            line += f"; this machine: {cpus:g} CPUs, {gpus or 0:g} GPUs → {conc.max_concurrent} concurrent trials"
        except SpecError as exc:
            line += f"; this machine cannot run it: {exc}"
    out.append(line)
    fixed = {k: v for k, v in {**plan.fixed, **plan.sets}.items() if k not in plan.swept}
    out.append("fixed: " + ", ".join(f"{k}={v}" for k, v in fixed.items()))
    out += ["protocol card:"] + [f"  {line}" for line in plan_card(plan).lines()]
    if spec.search.sampled:
        s = spec.search
        out.append(f"search: {search_kind(s.kind).describe(s)}, {plan.num_trials} trials, seed {spec.seeds[0]}, over:")
        for key, p in s.space.items():
            rng = f"{p.choices}" if p.type == "categorical" else f"[{p.low:g}, {p.high:g}]"
            out.append(f"  {key}: {p.type} {rng}")
    elif plan.sequential is not None:
        out += rule
    else:
        out.append(
            f"search: grid, {plan.num_trials} trials "
            f"({plan.num_trials // len(spec.seeds)} cells × {len(spec.seeds)} seeds):"
        )
    if not spec.search.sampled:
        for i, cell in enumerate(plan.cells, 1):
            values = ", ".join(f"{k}={v}" for k, v in cell.values.items())
            line = f"  {i:3d}. {cell.label}" + (f"   ({values})" if values else "")
            if plan.round_of(cell) > 1:
                line += f"   [round {plan.round_of(cell)}, if still open]"
            if cell.paper_label and spec.paper:
                numbers = ", ".join(f"{k} {v:g}" for k, v in cell.paper.items() if k.count("/") == 1)
                line += f"   [paper {spec.paper.table} · {cell.paper_label}: {numbers}]"
            out.append(line)
        if plan.grid_trials is not None:
            out.append(
                f"  … and {plan.num_trials - len(plan.cells)} more trials, each checked (a dry-run lists the first "
                f"{len(plan.cells)}; their inputs and memory stand for the rest)"
            )
    return wrapped("\n".join(out))


def _split(plan: SweepPlan) -> str:
    """The held-out split the trials are scored on (``data.eval_split``), the tuning split said as such."""
    split = {**plan.fixed, **plan.sets}.get("data.eval_split", "val")
    if split == "tune":
        return ("the tuning split (data.eval_split=tune: objects procedural/<category>/tune/…, none of the val "
                "objects a table reports)")
    return f"the {split} split (data.eval_split={split})"


def _scheduler(plan: SweepPlan) -> str:
    """The scheduler and where it may stop a trial, or, in one line, that under this profile it stops none."""
    sch, prof = plan.spec.scheduler, plan.profile
    if sch.kind == "none":
        return "none"
    _, total, every = prof.time_axis
    at, unit, end = ("step ", "", "the last step") if prof.compute_s is None else ("", " s of compute", "the budget")
    stops = sch.stops(total, every)
    if stops:
        return f"{sch.kind}, may stop a trial at {at}{', '.join(f'{s:g}' for s in stops)} of {total:g}{unit}"
    return (f"{sch.kind} stops no trial under profile {prof.name}: its first rung ({at}"
            f"{sch.grace_evals * every:g}{unit}) is not before {end} ({total:g}{unit})")


def wrapped(text: str, width: int = 120) -> str:
    """``text`` with every line over ``width`` UTF-8 bytes (→, λ, × are two or three) folded at spaces, each
    continuation indented two more; a word longer than the room (a long path) stays whole."""
    return "\n".join(_fold(line, width) for line in text.splitlines())


def _fold(line: str, width: int) -> str:
    indent = line[: len(line) - len(line.lstrip())] + "  "
    for room in range(width, width // 2, -1):
        folded = textwrap.fill(line, room, subsequent_indent=indent, break_long_words=False, break_on_hyphens=False)
        if max(len(part.encode()) for part in folded.splitlines() or [""]) <= width:
            break
    return folded
