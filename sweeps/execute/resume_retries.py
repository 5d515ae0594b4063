"""Errored trials on ``--resume``: each is retried once per resume, from its last checkpoint, until it has been
retried ``failure.max_retries`` times; then it is given up and stays failed.

Within one run Tune already restarts a failed trial up to ``failure.max_retries`` times
(``FailureConfig(max_failures=…)``); a trial that still fails ends as ERROR. Tune's restore can only resume every
errored trial or none (``Tuner.restore(resume_errored=…)``) and keeps no count across resumes, so the count per
trial is kept in the sweep folder (:data:`RECORD`, JSON: trial id → retries spent on resume). Where some errored
trials are retried and others given up in the same resume, Tune requeues them all and a given-up trial's
trainable refuses at once (:func:`refusing`), so it ends failed again without training.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NamedTuple

import ray.tune

from cdm.io.json import parse_json
from sweeps.store.files import StoreError, exists, read_record, write_record

__all__ = ["RECORD", "Retries", "RetriesSpent", "plan_retries", "refusing", "retry_errored"]

RECORD = "resume_retries.json"
"""The sweep folder's count of retries spent on resume, per trial id."""


class RetriesSpent(RuntimeError):
    """A given-up trial's trainable, requeued by Tune with the retried ones: it ends failed without training."""


class Retries(NamedTuple):
    """What one ``--resume`` does with the sweep's errored trials."""

    retried: list[str]
    """Trial ids retried now."""
    given_up: list[str]
    """Trial ids left failed: their ``failure.max_retries`` retries are spent."""
    spent: dict[str, int]
    """Retries spent on resume per trial id, this resume's counted."""


def plan_retries(errored: Iterable[str], spent: dict[str, int], max_retries: int) -> Retries:
    """Which of the ``errored`` trial ids a resume retries: those retried fewer than ``max_retries`` times before."""
    errored = sorted(errored)
    retried = [t for t in errored if spent.get(t, 0) < max_retries]
    return Retries(retried, [t for t in errored if t not in retried],
                   {**spent, **{t: spent.get(t, 0) + 1 for t in retried}})


def _record(sweep_dir: str) -> str:
    return f"{sweep_dir}/{RECORD}"


def read_spent(sweep_dir: str) -> dict[str, int]:
    """The record's retries per trial id; ``{}`` where none was written (no resume retried a trial yet).

    Raises:
        StoreError: the record is not a JSON object of trial id → count ≥ 0.
    """
    location = _record(sweep_dir)
    if not exists(location):
        return {}
    data = parse_json(read_record(location), "resume retries", Path(RECORD))
    if not isinstance(data, dict) or not all(isinstance(v, int) and v >= 0 for v in data.values()):
        raise StoreError(f"--resume: {location} is not a count of retries per trial (JSON object of trial id → "
                         "integer ≥ 0); remove it to count from 0")
    return data


def _write_spent(sweep_dir: str, spent: dict[str, int]) -> None:
    write_record(_record(sweep_dir), json.dumps(spent, indent=1, sort_keys=True) + "\n")


def _errored(sweep_dir: str) -> dict[str, dict[str, Any]]:
    """Trial id → config of each trial Tune's state at ``sweep_dir`` holds as errored."""
    analysis = ray.tune.ExperimentAnalysis(sweep_dir)
    return {t.trial_id: t.config for t in analysis.trials if t.status == "ERROR"}


def retry_errored(sweep_dir: str, max_retries: int, label: Callable[[dict[str, Any]], str]) -> tuple[bool, dict]:
    """Decide and say which errored trials this resume retries, and count them in the sweep folder.

    Returns:
        (whether Tune resumes errored trials, trial id → why a given-up one refuses to run) for
        ``Tuner.restore(resume_errored=…)`` and :func:`refusing`. ``label``: a trial config's cell label.
    """
    errored = _errored(sweep_dir)
    if not errored:
        return False, {}
    retries = plan_retries(errored, read_spent(sweep_dir), max_retries)
    names = {t: label(errored[t]) for t in errored}
    if retries.retried:
        print(f"--resume: retrying {len(retries.retried)} errored trial(s) from their last checkpoint: "
              + ", ".join(f"{names[t]} (retry {retries.spent[t]} of {max_retries})" for t in retries.retried),
              flush=True)
        _write_spent(sweep_dir, retries.spent)
    reasons = {}
    for t in retries.given_up:
        reasons[t] = (f"given up: retried {retries.spent.get(t, 0)} time(s) on --resume, failure.max_retries is "
                      f"{max_retries}")
        print(f"--resume: {names[t]} stays failed, {reasons[t]}", flush=True)
    return bool(retries.retried), reasons if retries.retried else {}


def refusing(trainable: Callable, given_up: dict[str, str]) -> Callable:
    """``trainable`` (a Tune function trainable ``(config, setup)``), refusing the trials of ``given_up``.

    ``functools.wraps`` keeps its name: Tune's restore refuses a trainable of another name than the sweep's.
    """

    @functools.wraps(trainable)
    def guarded(config: dict[str, Any], setup: Any) -> None:
        reason = given_up.get(ray.tune.get_context().get_trial_id())
        if reason is not None:
            raise RetriesSpent(reason)
        return trainable(config, setup)

    return guarded
