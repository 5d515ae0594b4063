"""The MLflow store a sweep logs to: its URI resolved and checked before any run exists, and the one client every
reader and writer of the record opens (:func:`client`).

A busy SQLite store is waited on, not fatal. Python's ``sqlite3`` gives up on a locked database after 5 s
("database is locked"), and MLflow's SQLAlchemy store passes that on: another process holding the store for
45 s failed both running trials of a sweep and left their child runs RUNNING. :func:`client` therefore sets
SQLite's own busy timeout (``PRAGMA busy_timeout``: the library retries with back-off until it passes) to
:data:`BUSY_TIMEOUT_S` on every SQLite connection SQLAlchemy opens in this process, MLflow's included;
:func:`check_not_locked` waits the same at a sweep's start and then says so in one line.

SQLite skips that wait where waiting could deadlock: a transaction that has read and now wants to write while
another writer waits for its readers to finish gets "database is locked" at once (a smoke sweep's trials failed
so, 2 s into another writer's 45 s hold). :class:`PatientClient` therefore also retries each MLflow call that
failed so, with back-off, for up to :data:`BUSY_TIMEOUT_S` (the failed transaction was rolled back: nothing is
logged twice). Two trials logging the same evaluation set (``log_inputs``) at once both find its dataset row
missing and both insert it; the later insert fails the table's unique key (seen in a 2-CPU smoke sweep). Its
transaction was rolled back too, and the retry finds the row and links it: retried the same way.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
import os
import sqlite3
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cdm.io.json import parse_json
from sweeps.store.files import StoreError, one_line, writable_folder

__all__ = [
    "BUSY_TIMEOUT_S", "EXPERIMENT_KIND", "RETRIED", "SOURCE_NAME", "TRACKING_SCHEMES", "WORKFLOW", "PatientClient",
    "artifact_location", "check_not_locked", "check_parent_run", "check_tracking_uri",
    "client", "experiment", "log_params", "resolve_tracking_uri", "retry_when_busy", "source_tags", "ui_command",
    "ui_link", "wait_when_busy",
]

TRACKING_SCHEMES = ("sqlite", "file", "http", "https", "postgresql", "mysql", "mssql")
"""MLflow stores a sweep can log to."""

DB_DRIVERS = {"postgresql": "psycopg2", "mysql": "MySQLdb", "mssql": "pyodbc"}
"""SQLAlchemy's default driver module of each database scheme MLflow takes (``scheme+driver`` names another)."""

BUSY_TIMEOUT_S = 120.0
"""How long a write waits for another writer of the SQLite store (MLflow UI, a second sweep, a backup)."""

RETRIED = ("database is locked", "UNIQUE constraint failed: datasets.")
"""The MLflow errors another writer causes and a retry clears (the module's docstring says why)."""

_BATCH = 100  # MLflow's limit of params per log_batch call


def resolve_tracking_uri(cli: str | None, cwd: Path | None = None) -> str:
    """``--tracking-uri``, else ``MLFLOW_TRACKING_URI``, else ``sqlite:///<cwd>/mlflow.db``; always absolute.

    A relative SQLite path would resolve inside each Ray trial's own working directory, so it is
    made absolute against ``cwd`` here, on the driver.
    """
    cwd = (cwd or Path.cwd()).resolve()
    uri = cli or os.environ.get("MLFLOW_TRACKING_URI") or "sqlite:///mlflow.db"
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        uri = f"sqlite:///{cwd / uri.removeprefix('sqlite:///')}"
    return uri


def check_tracking_uri(uri: str) -> None:
    """Refuse an MLflow URI this sweep could not log to, before any run is created: a scheme MLflow cannot open,
    a folder (SQLite, files) that cannot be written, a server that is no MLflow server, a database driver not
    installed; a SQLite store that another writer holds is waited on (:data:`BUSY_TIMEOUT_S`)."""
    scheme = urllib.parse.urlsplit(uri).scheme.split("+")[0]
    if scheme not in TRACKING_SCHEMES:
        raise StoreError(f"--tracking-uri {uri}: unsupported scheme {scheme or '(none)'!r}; use one of "
                         + ", ".join(f"{s}://" for s in TRACKING_SCHEMES))
    if scheme == "sqlite":
        writable_folder(Path(uri.removeprefix("sqlite:///")).parent, "--tracking-uri")
        check_not_locked(Path(uri.removeprefix("sqlite:///")))
    elif scheme == "file":
        writable_folder(Path(urllib.parse.urlsplit(uri).path), "--tracking-uri")
    elif scheme in ("http", "https"):
        _check_mlflow_server(uri)
    elif scheme in DB_DRIVERS:
        dialect = urllib.parse.urlsplit(uri).scheme
        driver = dialect.split("+", 1)[1] if "+" in dialect else DB_DRIVERS[scheme]
        if importlib.util.find_spec(driver) is None:
            raise StoreError(f"--tracking-uri {uri}: its database driver {driver!r} is not installed; "
                             f"`pip install` it (or name an installed one: {scheme}+<driver>://…)")


def _check_mlflow_server(uri: str) -> None:
    """An HTTP(S) server that answers ``/health`` and MLflow's REST API (any server may answer ``/health``)."""
    base = uri.rstrip("/")
    try:
        with urllib.request.urlopen(f"{base}/health", timeout=10):
            pass
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise StoreError(f"--tracking-uri {uri}: no MLflow server answers there ({reason}); start one "
                         "(`mlflow server --host 127.0.0.1 --port 5000`) or give another URI") from None
    try:
        with urllib.request.urlopen(f"{base}/api/2.0/mlflow/experiments/search?max_results=1", timeout=10) as reply:
            answer = parse_json(reply.read(1 << 20), f"--tracking-uri {uri}", "the server's answer")
    except (urllib.error.URLError, OSError, ValueError) as exc:
        answer = one_line(exc)
    if not isinstance(answer, dict):
        raise StoreError(f"--tracking-uri {uri}: the server there answers /health but not MLflow's API "
                         f"(experiments/search: {str(answer)[:100]}); give the URI of an MLflow server")


def check_parent_run(uri: str, run_id: str) -> None:
    """Refuse ``--resume`` when the store ``uri`` lacks the sweep's parent run ``run_id``; a SQLite file or
    store folder that does not exist is not created to find out."""
    split = urllib.parse.urlsplit(uri)
    local = (
        uri.removeprefix("sqlite:///") if split.scheme == "sqlite" else split.path if split.scheme == "file" else None
    )
    if local is not None and not Path(local).exists():
        raise StoreError(f"--resume: the MLflow store {uri} does not exist, so it lacks the sweep's parent run "
                         f"{run_id}; pass the --tracking-uri the sweep started with")
    from mlflow.exceptions import MlflowException

    try:
        client(uri).get_run(run_id)
    except MlflowException as exc:
        raise StoreError(f"--resume: the MLflow store {uri} has no parent run {run_id} "
                         f"({one_line(exc)[:160]}); pass the --tracking-uri the sweep started with") from None


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
        StoreError: another process held the write lock throughout.
    """
    if not path.is_file():
        return
    wait_s = BUSY_TIMEOUT_S
    connection = sqlite3.connect(path, timeout=wait_s, isolation_level=None)
    try:
        connection.execute("BEGIN IMMEDIATE")
        connection.execute("ROLLBACK")
    except sqlite3.OperationalError as exc:
        raise StoreError(f"--tracking-uri sqlite:///{path}: {exc} by another writer for {wait_s:g} s; stop it "
                         "(another sweep, a script) or wait, then start again") from None
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


def client(uri: str) -> PatientClient:
    """The client of the store ``uri`` every reader and writer of a sweep's record uses: a busy SQLite store is
    waited on (:func:`wait_when_busy`, :class:`PatientClient`), and MLflow's artifact transfers draw no
    progress bar (a sweep downloads one small file per trial, and each trial's model logging copies its
    checkpoint through MLflow's downloader: bars from every trial would reach the sweep's terminal)."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    wait_when_busy()
    return PatientClient(uri)


def ui_command(uri: str) -> str:
    """The command that shows this tracking store in a browser, bound to loopback only."""
    if uri.startswith("sqlite:"):
        return f"mlflow ui --backend-store-uri {uri} --host 127.0.0.1 --port 5000"
    return f"open {uri} in a browser"


EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
"""The experiment tag MLflow 3 keeps an experiment's kind in (its UI's kind selector writes it: "Machine
learning", not "GenAI apps & agents"). MLflow 3.17's own UI chooses its workflow per browser instead
(``localStorage`` ``mlflow.workflowType``, default GenAI; the URL's ``workflowType`` wins), so every link
the runner prints also carries :data:`WORKFLOW`."""

WORKFLOW = "workflowType=machine_learning"
"""The URL parameter that opens MLflow 3's model-training workflow (Runs, Models) whatever the browser
chose before: no Sessions, Judges, Prompts or AI Gateway, the runs under "Runs", not "Evaluation runs"."""


def ui_link(path: str) -> str:
    """``path`` of the MLflow UI (``#/experiments/…``) opening in the model-training workflow (:data:`WORKFLOW`)."""
    return path + ("&" if "?" in path else "?") + WORKFLOW


def artifact_location(uri: str, name: str) -> str | None:
    """Where a new experiment ``name`` of the store ``uri`` keeps its artifacts: beside a SQLite database
    (``<its folder>/mlruns/<name>``) rather than in whatever directory the driver ran from; None: the store's
    own default (a tracking server's artifact store)."""
    if uri.startswith("sqlite:///"):
        return (Path(uri.removeprefix("sqlite:///")).parent / "mlruns" / name).as_uri()
    return None


def experiment(store: PatientClient, name: str, uri: str) -> str:
    """The experiment ``name``'s id, created if needed, tagged a model-training one (:data:`EXPERIMENT_KIND`),
    also when an older sweep created it."""
    found = store.get_experiment_by_name(name)
    if found is not None:
        experiment_id = found.experiment_id
    else:
        experiment_id = store.create_experiment(name, artifact_location=artifact_location(uri, name))
    store.set_experiment_tag(experiment_id, *EXPERIMENT_KIND)
    return experiment_id


SOURCE_NAME = "sweeps/run.py"
"""MLflow's ``mlflow.source.name`` of a sweep's runs, parent and children: the entry point that starts a sweep
(``cdm-lab sweep`` runs it), from the checkout ``mlflow.source.git.commit`` names."""


def source_tags(git_commit: str) -> dict[str, str]:
    """MLflow's own source tags (what ``mlflow.start_run`` sets from its context, which a run created through
    a client lacks): the entry point, ``LOCAL``, and the commit where the checkout has one (``git_commit`` of
    :func:`cdm.provenance.code_version`; ``unknown`` outside git: no commit tag then). The ``repro.git_commit``
    tag stays beside it: ``rerun`` reads the ``repro.*`` record whole."""
    tags = {"mlflow.source.name": SOURCE_NAME, "mlflow.source.type": "LOCAL"}
    return tags | ({"mlflow.source.git.commit": git_commit} if git_commit != "unknown" else {})


def log_params(store: PatientClient, run_id: str, values: dict[str, Any]) -> None:
    """``values`` as params of the run (MLflow keeps a param as text), in batches of MLflow's limit."""
    from mlflow.entities import Param

    params = [Param(k, str(v)) for k, v in values.items()]
    for i in range(0, len(params), _BATCH):
        store.log_batch(run_id, params=params[i:i + _BATCH])
