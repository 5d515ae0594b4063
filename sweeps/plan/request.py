"""The command line's sweep request checked and turned into its plan, before Ray starts.

Every check of the arguments of a sweep (``--profile``/``--smoke``, ``--out`` on a cluster, ``--set``,
``--resume`` against ``sweep.json``, ``--budget``, the trial cap, the machine's memory) lives here; each
refusal is one :class:`RequestError` that ``sweeps/run.py`` prints as ``error: …`` with exit code 2,
having started and written nothing.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cdm.config import ConfigError, parse_override
from cdm.memory import check_memory
from sweeps.plan.address import AddressError, check_form, given_address
from sweeps.plan.budget import SeedBudget, check_budget, parse_budget
from sweeps.plan.limits import LISTED_TRIALS, LimitError, check_progress, check_set_text, check_trials, count_trials
from sweeps.plan.preflight import check_inputs
from sweeps.plan.resources import plan_concurrency
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import Spec, load_spec
from sweeps.plan.trials import SweepPlan, expand
from sweeps.store.files import StoreError, exists, is_uri, read_state, sweep_location

__all__ = ["STATE_FILE", "RequestError", "SweepRequest", "missing_inputs", "plan_request"]

STATE_FILE = "sweep.json"
"""What ``--resume`` reads in the sweep folder: the spec, ``--set`` values, budget and MLflow run it started with."""


class RequestError(Exception):
    """A request refused before anything starts; the message names the argument or file and what is allowed."""


@dataclass(frozen=True)
class SweepRequest:
    """A checked sweep request: its plan (every trial's config built), where it is kept, how it resumes."""

    plan: SweepPlan
    sweep_dir: str
    """``<storage>/<spec name>/<profile>``: a path or an object-store URI."""
    sets: dict[str, Any]
    """``--set`` values (a resumed sweep's: those it started with)."""
    budget: SeedBudget | None
    remote: bool
    """Trials run on a cluster joined by address (``--address`` or ``RAY_ADDRESS``)."""
    state: dict[str, Any] | None = None
    """A resumed sweep's ``sweep.json``, read and checked once; None for a new sweep."""
    tracking_uri: str | None = None
    """The MLflow store asked for: ``--tracking-uri``, else a resumed sweep's own (it keeps logging where it
    started, wherever it is resumed from); None: the default one."""

    @property
    def state_file(self) -> str:
        return f"{self.sweep_dir}/{STATE_FILE}"


def plan_request(args: argparse.Namespace) -> SweepRequest:
    """The sweep ``args`` ask for, every trial's config built and checked; :class:`RequestError` otherwise."""
    if args.smoke and args.profile not in (None, "smoke"):
        raise RequestError(f"--smoke means --profile smoke; got --profile {args.profile} too")
    profile = "smoke" if args.smoke else (args.profile or "local")
    remote = _remote(args)
    try:
        spec = load_spec(args.spec)
        sweep_dir = sweep_location(args.storage, spec.name, profile)
        for text in args.set:
            check_set_text(text)
        sets = dict(parse_override(text) for text in args.set)
        state = None
        if args.resume:
            state, spec = _resumed(args, sweep_dir, sets)
            sets = state["sets"]
        if args.until_settled:
            spec = spec.until_settled()
        given = state.get("budget") if state is not None else args.budget
        budget = None if given is None else parse_budget(given)  # an empty --budget= is refused, not taken as none
        check_trials(spec, args.max_cells)
        plan = _expand(spec, profile, sets, args.dry_run)
        check_budget(plan, budget)
        if not remote:  # a cluster's nodes have their own memory; this machine's says nothing of them
            check_memory(plan.configs, _local_concurrency(plan))
    except (SpecError, ConfigError, LimitError, StoreError) as exc:
        raise RequestError(str(exc)) from None
    uri = args.tracking_uri or (state or {}).get("tracking_uri")
    return SweepRequest(plan, sweep_dir, sets, budget, remote, state, uri)


def _remote(args: argparse.Namespace) -> bool:
    """Whether the trials run on a cluster joined by address; its form, and ``--out`` on it, checked."""
    given = given_address(args.address)
    if given is None:
        return False
    try:
        check_form(*given)  # whether a cluster answers there is asked right before Ray joins it (cluster.py)
    except AddressError as exc:
        raise RequestError(str(exc)) from None
    if not args.dry_run and not is_uri(args.storage) and not Path(args.storage).is_absolute():
        # Under `ray job submit` the driver's working directory is the job's temporary copy of the
        # repository: checkpoints there vanish with the job and other nodes never see them.
        raise RequestError(f"--out {args.storage}: on a cluster give an absolute path that every node shares "
                           "(e.g. /mnt/shared/results) or an object-store URI (s3://bucket/results)")
    return True


def _expand(spec: Spec, profile: str, sets: dict[str, Any], dry_run: bool) -> SweepPlan:
    """:func:`expand`; a dry run of more grid trials than it lists checks them one at a time, saying so."""
    count = count_trials(spec)[0]
    if not dry_run or count <= LISTED_TRIALS or spec.search.sampled:
        return expand(spec, profile, sets)
    print(f"checking up to {count} trials one at a time (listing the first {LISTED_TRIALS}) …", flush=True)
    return expand(spec, profile, sets, keep=LISTED_TRIALS, each=check_progress(count))


def _resumed(args: argparse.Namespace, sweep_dir: str, sets: dict[str, Any]) -> tuple[dict[str, Any], Spec]:
    """The ``sweep.json`` of the sweep ``--resume`` continues and its spec as it started (even if the file was
    edited since: trials must stay the same), checked to validate."""
    state_file = f"{sweep_dir}/{STATE_FILE}"
    if not exists(state_file):
        raise RequestError(f"--resume: {sweep_dir} holds no sweep to resume (no {STATE_FILE})")
    if sets:
        raise RequestError("--resume continues a sweep with the spec and --set values it started with; drop --set")
    if args.until_settled or args.budget is not None:
        raise RequestError(
            "--resume continues a sweep with the seeds and budget it started with; drop --until-settled and --budget"
        )
    state = read_state(state_file)
    try:
        return state, Spec.model_validate(state["spec"])
    except ValidationError as exc:
        raise RequestError(
            f"--resume: {state_file} is damaged ({' '.join(str(exc).split())}); remove the folder to start over"
        ) from None


def _local_concurrency(plan: SweepPlan) -> int:
    """Trials this machine runs at once (GPUs not counted: the memory check is about host RAM)."""
    try:
        return plan_concurrency(plan.profile.resources, os.cpu_count() or 1, 1e9, plan.num_trials).max_concurrent
    except SpecError:
        return 1


def missing_inputs(plan: SweepPlan, remote: bool, dry_run: bool) -> str | None:
    """:func:`sweeps.plan.preflight.check_inputs`: a sweep refuses absent inputs (:class:`RequestError`), a dry
    run still plans (the card, the plan, the estimate) and returns what is missing, said at its end."""
    try:
        check_inputs(plan, remote)
    except ValueError as exc:
        if not dry_run:
            raise RequestError(str(exc)) from None
        return str(exc)
    return None
