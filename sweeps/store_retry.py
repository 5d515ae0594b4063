"""A busy SQLite MLflow store is waited on, not fatal.

Python's ``sqlite3`` gives up on a locked database after 5 s ("database is locked"), and MLflow's
SQLAlchemy store passes that on: another process holding the store for 45 s failed both running
trials of a sweep and left their child runs RUNNING. :func:`wait_when_busy` sets SQLite's own busy
timeout (``PRAGMA busy_timeout``: the library retries with back-off until it passes) to
:data:`BUSY_TIMEOUT_S` on every SQLite connection SQLAlchemy opens in this process, MLflow's
included; :func:`check_not_locked` waits the same at a sweep's start and then says so in one line.

SQLite skips that wait where waiting could deadlock: a transaction that has read and now wants to
write while another writer waits for its readers to finish gets "database is locked" at once (a
smoke sweep's trials failed so, 2 s into another writer's 45 s hold). :class:`PatientClient` therefore
also retries each MLflow call that failed so, with back-off, for up to :data:`BUSY_TIMEOUT_S` (the
failed transaction was rolled back: nothing is logged twice).

Two trials logging the same evaluation set (``log_inputs``) at once both find its dataset row missing
and both insert it; the later insert fails the table's unique key (seen in a 2-CPU smoke sweep). Its
transaction was rolled back too, and the retry finds the row and links it: retried the same way.
"""

from __future__ import annotations

import functools
import logging
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["BUSY_TIMEOUT_S", "RETRIED", "PatientClient", "StoreBusy", "check_not_locked", "retry_when_busy",
           "wait_when_busy"]

BUSY_TIMEOUT_S = 120.0
"""How long a write waits for another writer of the SQLite store (MLflow UI, a second sweep, a backup)."""

RETRIED = ("database is locked", "UNIQUE constraint failed: datasets.")
"""The MLflow errors another writer causes and a retry clears (the module's docstring says why)."""


class StoreBusy(RuntimeError):
    """The SQLite store stayed locked by another writer for the whole wait."""


def _busy_timeout(dbapi_connection, connection_record) -> None:
    if isinstance(dbapi_connection, sqlite3.Connection):
        dbapi_connection.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")


def _not_locked(record: logging.LogRecord) -> bool:
    return "database is locked" not in record.getMessage()


def wait_when_busy() -> None:
    """Make every SQLite connection SQLAlchemy opens in this process wait for a busy store, and keep MLflow
    from logging a traceback for each "database is locked" that :func:`retry_when_busy` retries (idempotent)."""
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    if not event.contains(Engine, "connect", _busy_timeout):
        event.listen(Engine, "connect", _busy_timeout)
        logging.getLogger("mlflow.store.db.utils").addFilter(_not_locked)


def check_not_locked(path: Path) -> None:
    """Wait up to :data:`BUSY_TIMEOUT_S` to take (and at once give back) the write lock of the SQLite file
    ``path``; a missing file passes (MLflow creates it).

    Raises:
        StoreBusy: another process held the write lock throughout.
    """
    if not path.is_file():
        return
    wait_s = BUSY_TIMEOUT_S
    connection = sqlite3.connect(path, timeout=wait_s, isolation_level=None)
    try:
        connection.execute("BEGIN IMMEDIATE")
        connection.execute("ROLLBACK")
    except sqlite3.OperationalError as exc:
        raise StoreBusy(f"MLflow store {path}: {exc} by another writer for {wait_s:g} s; stop it (another sweep, "
                        "a script) or wait, then start again") from None
    finally:
        connection.close()


def retry_when_busy(call: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``call(*args, **kwargs)``, again after 0.1, 0.2, … (at most 5) s while it fails with one of MLflow's
    :data:`RETRIED` errors, until :data:`BUSY_TIMEOUT_S` have passed; then, or on any other error, it is raised."""
    from mlflow.exceptions import MlflowException  # deferred: the CLI checks its input before importing MLflow

    deadline = time.monotonic() + BUSY_TIMEOUT_S
    pause = 0.1
    while True:
        try:
            return call(*args, **kwargs)
        except MlflowException as exc:
            if not any(text in str(exc) for text in RETRIED) or time.monotonic() + pause > deadline:
                raise
        time.sleep(pause)
        pause = min(2 * pause, 5.0)


class PatientClient:
    """An ``mlflow.MlflowClient`` of the store ``uri`` whose public methods go through :func:`retry_when_busy`."""

    def __init__(self, uri: str):
        from mlflow import MlflowClient

        self._client = MlflowClient(uri)

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._client, name)
        if name.startswith("_") or not callable(attr):
            return attr
        return functools.wraps(attr)(functools.partial(retry_when_busy, attr))
