"""The sweep's live progress line and a quiet terminal: trials done/running/failed, steps across
trials, elapsed and remaining time; Ray's and MLflow's boilerplate kept out of the output.

Trials push their step count (every ``train.log_every`` steps) to one small Ray actor, the
:class:`StepCounter`, named after the sweep's parent run; the driver's :class:`SweepProgress` (a
Tune callback) reads it and redraws one line in place on a terminal, or prints one plain line a
minute when the output goes to a file. Remaining time comes from the runner's calibration
(:mod:`sweeps.plan.estimate`): the predicted wall time scaled by the share of steps still to run.
"""

from __future__ import annotations

import logging
import os
import re
import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO

import ray
import ray.tune
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from cdm.train import Callback
from sweeps.ray_internals import set_log_dedup

__all__ = [
    "QUIET_LOGGERS",
    "StepCounter",
    "StepReporter",
    "SweepProgress",
    "counter_name",
    "is_tty",
    "plain_log_handlers",
    "quiet_actor_exit",
    "quiet_environment",
    "quiet_loggers",
]

QUIET_LOGGERS = ("ray.train", "ray.tune", "mlflow", "alembic")
"""Loggers whose INFO lines are boilerplate in a sweep ("Checkpoint successfully created at", "Running
in local mode", MLflow's database set-up); their warnings and errors still show."""


def quiet_environment(tty: bool) -> None:
    """Environment read when Ray and MLflow are imported or start workers (which inherit it).

    Ray's legacy progress engine at ``verbose=0`` prints nothing (the new one still prints its config
    box and a TensorBoard hint); off a terminal, Ray's worker-line prefixes carry no colour codes.

    Progress lines of concurrent trials differ only in numbers, and Ray's log de-duplication would
    fold them into "[repeated 3x across cluster]", a suffix it colours green whatever
    ``RAY_COLOR_PREFIX`` says (and it holds the folded lines back into the next sweep's output). Ray
    reads ``RAY_DEDUP_LOGS`` once, on import, so in a process that imported Ray before (a notebook,
    the test suite, a second sweep) the driver's de-duplicator is switched here too, for every sweep.
    """
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    os.environ.setdefault("MLFLOW_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    set_log_dedup(os.environ["RAY_DEDUP_LOGS"].lower() in ("1", "true"))  # Ray's own parsing
    if not tty:
        os.environ.setdefault("RAY_COLOR_PREFIX", "0")


def quiet_loggers() -> None:
    """INFO of :data:`QUIET_LOGGERS` off in this process (the driver, and each trial's process)."""
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)


def quiet_actor_exit() -> None:
    """An exit Ray asks of this trial's process is not printed as an error; every other one still is.

    Tune stops an idle trial actor with SIGTERM, and Ray's handler raises ``SystemExit`` wherever the
    process stands. Raised inside a garbage-collection callback (a ``WeakSet``'s), it cannot propagate, and
    Python's ``sys.unraisablehook`` would print "Exception ignored … SystemExit: 1" with its traceback into
    the sweep's output after the trial finished well. Installed once per process.
    """
    hook = sys.unraisablehook
    if getattr(hook, "drops_exit", False):
        return

    def unraisable(info) -> None:
        if not isinstance(info.exc_value, SystemExit):
            hook(info)

    unraisable.drops_exit = True
    sys.unraisablehook = unraisable


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


class _NoColour(logging.Formatter):
    """A handler's own formatter with terminal colour codes taken out of what it writes."""

    def __init__(self, inner: logging.Formatter | None):
        super().__init__()
        self.inner = inner or logging.Formatter()

    def format(self, record: logging.LogRecord) -> str:
        return _ANSI.sub("", self.inner.format(record))


def plain_log_handlers() -> None:
    """No colour codes from any stream handler of this process (for output that is not a terminal).

    Ray colours the ``ray::…()`` line of every task error it formats (``RayTaskError``) whatever
    ``RAY_COLOR_PREFIX`` says, and Tune logs a failed trial's error with it.
    """
    loggers = [
        logging.getLogger(),
        *(x for x in logging.root.manager.loggerDict.values() if isinstance(x, logging.Logger)),
    ]
    for logger in loggers:
        for handler in logger.handlers:
            if isinstance(handler, logging.StreamHandler) and not isinstance(handler.formatter, _NoColour):
                handler.setFormatter(_NoColour(handler.formatter))


def counter_name(parent_run_id: str) -> str:
    return f"cdm-steps-{parent_run_id}"


@ray.remote(num_cpus=0)
class StepCounter:
    """Last step each trial reported, by trial label; holds no resources."""

    def __init__(self) -> None:
        self.steps: dict[str, int] = {}

    def record(self, label: str, step: int) -> None:
        self.steps[label] = step

    def snapshot(self) -> dict[str, int]:
        return dict(self.steps)


class StepReporter(Callback):
    """Trial side: each logged step to the sweep's :class:`StepCounter` (fire and forget)."""

    def __init__(self, parent_run_id: str, label: str):
        self.label = label
        try:
            self.counter = ray.get_actor(counter_name(parent_run_id))
        except ValueError:  # no sweep driver counting (a trial run on its own): nothing to report to
            self.counter = None

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        if self.counter is not None:
            self.counter.record.remote(self.label, step)


def _clock(seconds: float) -> str:
    seconds = int(max(0.0, seconds))
    return (
        f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
        if seconds >= 3600
        else f"{seconds // 60}:{seconds % 60:02d}"
    )


class SweepProgress(ray.tune.Callback):
    """Driver side: one progress line for the whole sweep, kept up to date by a background thread.

    Args:
        trials: trials of the sweep (a sequential sweep's worst case); ``steps``: training steps of each.
        label: trial → its label (the name trials report their steps under).
        round_of: trial → the round it runs in, and ``rounds`` the most there can be (a sequential
            sweep's, :meth:`sweeps.plan.trials.SweepPlan.round_of`); counted on the line when ``rounds > 1``.
        predicted_s: the calibrated wall-time estimate of the whole sweep (None: no remaining time).
        tty: redraw in place every ``refresh_s`` seconds; else one line each ``every_s`` seconds.
    """

    def __init__(self, parent_run_id: str, trials: int, steps: int, label: Callable[[object], str],
                 predicted_s: float | None, tty: bool, stream: TextIO | None = None,
                 refresh_s: float = 1.0, every_s: float = 60.0, round_of: Callable[[object], int] | None = None,
                 rounds: int = 1):
        self.trials, self.steps, self.label, self.predicted_s, self.tty = trials, steps, label, predicted_s, tty
        self.round_of, self.rounds, self.round = round_of, rounds, 0
        self.stream = stream or sys.stdout
        self.period = refresh_s if tty else every_s
        # On the driver's own node: Ray would place it on any node, and a lost worker node would take
        # the counter (and the line, and the sweep with it) down while its trials carry on elsewhere.
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        self.counter = StepCounter.options(name=counter_name(parent_run_id), scheduling_strategy=here).remote()
        self.running: set[str] = set()
        self.done: set[str] = set()
        self.failed: set[str] = set()
        self.finished_steps: dict[str, int] = {}
        self.started = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="sweep-progress", daemon=True)
        self._thread.start()

    def __reduce__(self):
        # Tune pickles its callbacks into the experiment state; the line (its thread, its actor) is
        # this driver's alone, so a restored experiment gets an inert callback in its place.
        return ray.tune.Callback, ()

    def _loop(self) -> None:
        while not self._stop.wait(self.period):
            self._draw()

    def line(self, steps_now: dict[str, int] | None = None) -> str:
        """``sweep: 1/5 done, 2 running, 0 failed · 1200/4000 steps · 3:05 elapsed, ~6 min left``; a
        sequential sweep's starts ``sweep: round 2 of ≤4 · 5/≤12 done`` (its totals are the worst case,
        and so is the time left)."""
        reported = {**(steps_now or {}), **self.finished_steps}
        done_steps = min(sum(reported.values()), self.trials * self.steps)
        total = self.trials * self.steps
        elapsed = time.monotonic() - self.started
        rounds = self.rounds > 1
        at_most = "≤" if rounds else ""
        text = (
            "sweep: "
            + (f"round {max(1, self.round)} of ≤{self.rounds} · " if rounds else "")
            + f"{len(self.done)}/{at_most}{self.trials} done, {len(self.running)} running, {len(self.failed)} failed"
            f" · {done_steps}/{at_most}{total} steps · {_clock(elapsed)} elapsed"
        )
        if self.predicted_s is not None:
            left = self.predicted_s * (1 - done_steps / total) if total else 0.0
            text += f", ~{left / 60:.1f} min left (calibrated{', at most' if rounds else ''})"
        return text

    def _draw(self) -> None:
        text = self.line(ray.get(self.counter.snapshot.remote()))
        if self.tty:  # cursor left at the start: the next line Ray forwards writes over this one
            self.stream.write("\x1b[2K" + text + "\r")
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def on_trial_start(self, iteration, trials, trial, **info) -> None:
        self.running.add(self.label(trial))
        if self.round_of is not None:
            self.round = max(self.round, self.round_of(trial))

    def _ended(self, trial, into: set[str]) -> None:
        label = self.label(trial)
        self.running.discard(label)
        into.add(label)
        # A trial stopped early or failed runs no more steps: its last reported step, not its budget.
        self.finished_steps[label] = int(trial.last_result.get("step", 0))

    def on_trial_complete(self, iteration, trials, trial, **info) -> None:
        self._ended(trial, self.done)

    def on_trial_error(self, iteration, trials, trial, **info) -> None:
        self._ended(trial, self.failed)

    def close(self) -> None:
        """Stop redrawing; print the final line (ending the in-place one on a terminal)."""
        self._stop.set()
        self._thread.join()
        self._draw()
        if self.tty:
            self.stream.write("\n")
        ray.kill(self.counter)


def is_tty(stream: TextIO) -> bool:
    return hasattr(stream, "isatty") and stream.isatty()


