"""How a sweep that stops early ends: a full disk recognised as such, an interrupted sweep's children
closed as KILLED, the command that resumes it, and a start that ran no trial removed."""

from __future__ import annotations

import errno
import shlex
import shutil
from pathlib import Path

from sweeps.store.files import is_uri, one_line

__all__ = ["discard_start", "kill_running_children", "no_space_left", "one_line", "resume_command"]


def no_space_left(exc: BaseException) -> bool:
    """``exc`` or one it was raised from is a full disk: ``ENOSPC``, or torch's ``PytorchStreamWriter``
    "unexpected pos" (its only report of a write that found no space) and Ray's wrapped copies of either."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "No space left on device" in str(exc) or "unexpected pos" in str(exc):
            return True
        exc = exc.__cause__ or exc.__context__
    return False

def discard_start(sweep_dir: str) -> None:
    """Remove the sweep folder a start that ran no trial wrote (``sweep.json``, ``plan.json``, the shared
    cache), so the same command, once its input is fixed, is not refused as "already holds a sweep"."""
    if is_uri(sweep_dir):
        from pyarrow import fs

        filesystem, path = fs.FileSystem.from_uri(sweep_dir)
        filesystem.delete_dir(path)
    else:
        shutil.rmtree(sweep_dir, ignore_errors=True)

def resume_command(spec: Path, profile: str, storage: str) -> str:
    """The command that continues this sweep: the storage too, or the resume would look in ./results."""
    return shlex.join(["python", "sweeps/run.py", str(spec), "--profile", profile, "--out", storage, "--resume"])

def kill_running_children(sweep_run) -> int:
    """Close as KILLED the child runs of ``sweep_run`` (a :class:`sweeps.store.sweep_run.SweepRun`) still RUNNING
    once Tune has stopped (interrupted trials); ``--resume`` reopens each. Returns how many."""
    running = sweep_run.client.search_runs(
        [sweep_run.experiment_id], max_results=10_000,
        filter_string=f"tags.mlflow.parentRunId = '{sweep_run.run_id}' and attributes.status = 'RUNNING'")
    for child in running:
        sweep_run.client.set_terminated(child.info.run_id, status="KILLED")
    return len(running)
