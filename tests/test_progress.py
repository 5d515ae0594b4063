"""The sweep's terminal hygiene (sweeps/execute/progress.py): output that is not a terminal carries no colour codes."""

from __future__ import annotations

import io
import logging

from sweeps.execute.progress import plain_log_handlers


def test_plain_log_handlers_take_colour_codes_out_of_every_stream_handler_once():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(levelname)s -- %(message)s"))
    logger = logging.getLogger("test_progress.colours")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        plain_log_handlers()
        plain_log_handlers()  # a second sweep in the same process wraps nothing twice
        try:
            raise RuntimeError("\x1b[36mray::ImplicitFunc.train()\x1b[39m (pid=1)")
        except RuntimeError:
            logger.exception("Trial task failed for \x1b[1mtrial\x1b[0m")
    finally:
        logger.removeHandler(handler)
    text = stream.getvalue()
    assert "\x1b[" not in text
    assert (
        text.startswith("ERROR -- Trial task failed for trial\n")
        and "RuntimeError: ray::ImplicitFunc.train() (pid=1)" in text
    )
    assert type(handler.formatter.inner) is logging.Formatter  # the handler's own format, kept inside


def test_an_exit_raised_where_python_cannot_propagate_it_is_dropped_and_other_errors_still_reach_the_hook(
    monkeypatch,
):
    import gc
    import sys
    import weakref

    from sweeps.execute.progress import quiet_actor_exit

    seen: list[type] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: seen.append(type(info.exc_value)))
    quiet_actor_exit()
    quiet_actor_exit()  # a reused actor runs its next trial: still one wrapper

    class Held:
        pass

    def unraisable(error: BaseException) -> None:
        # A weakref callback runs when its object is collected; what it raises is "unraisable", as Ray's
        # SIGTERM handler's SystemExit is when the signal lands inside a WeakSet's callback.
        held = Held()
        ref = weakref.ref(held, lambda _: (_ for _ in ()).throw(error))
        del held
        gc.collect()
        assert ref() is None

    unraisable(SystemExit(1))
    assert seen == []
    unraisable(ValueError("a real error"))
    assert seen == [ValueError]
