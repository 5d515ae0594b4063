"""Ctrl-C and SIGTERM end a command the same way: as :class:`KeyboardInterrupt` where it runs, so every
``finally`` on the way out runs (a temporary file removed, a run closed) and the command ends in one line.

Python's default for SIGTERM (what ``kill``, ``timeout`` and batch schedulers send) ends the process at
once, skipping ``finally``: a write under way would leave its temporary file behind.
"""

from __future__ import annotations

import functools
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import ParamSpec

__all__ = ["INTERRUPTED", "interruptible", "said_interrupted", "sigterm_as_ctrl_c", "take_sigterm_as_ctrl_c"]

P = ParamSpec("P")

Handler = Callable[[int, FrameType | None], object] | int | None
"""What ``signal.signal`` returns: a handler, ``SIG_DFL``/``SIG_IGN``, or None (not set from Python)."""

INTERRUPTED = 130
"""Exit status of an interrupted command: 128 + SIGINT, what a shell reports for Ctrl-C."""


def _as_ctrl_c(signum: int, frame: FrameType | None) -> None:
    signal.raise_signal(signal.SIGINT)


def take_sigterm_as_ctrl_c() -> Handler:
    """From now on SIGTERM is taken as Ctrl-C: raised as SIGINT, so whatever handles Ctrl-C (Python's
    ``KeyboardInterrupt``, Tune's graceful stop) handles it; returns the previous handler, to restore."""
    return signal.signal(signal.SIGTERM, _as_ctrl_c)


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """:func:`take_sigterm_as_ctrl_c` within the block; the previous handler is restored after."""
    previous = take_sigterm_as_ctrl_c()
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def said_interrupted(command: str) -> int:
    """Say that ``command`` stopped on Ctrl-C or SIGTERM, in one line; returns :data:`INTERRUPTED`."""
    print(f"interrupted: {command} stopped on Ctrl-C or SIGTERM", file=sys.stderr)
    return INTERRUPTED


def interruptible(command: str) -> Callable[[Callable[P, int]], Callable[P, int]]:
    """A command's ``main`` that Ctrl-C or SIGTERM ends in one line (:func:`said_interrupted`, exit
    :data:`INTERRUPTED`), its ``finally`` blocks run on the way out; ``command`` is how the user typed it."""

    def wrap(main: Callable[P, int]) -> Callable[P, int]:
        @functools.wraps(main)
        def run(*args: P.args, **kwargs: P.kwargs) -> int:
            try:
                with sigterm_as_ctrl_c():
                    return main(*args, **kwargs)
            except KeyboardInterrupt:
                return said_interrupted(command)

        return run

    return wrap
