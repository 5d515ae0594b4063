"""Trust boundaries of a sweep (issue 33): no file planted in the storage or in the shared temporary
folder makes the runner overwrite, execute or kill. Each test plants the hostile file or state in
tmp and runs ``sweeps/run.py`` (or the guarding function), then asserts exit 2 with one ``error:``
line, the victim untouched, the planted code not run, the folder unescaped, Ray never started."""

from __future__ import annotations

import contextlib
import http.server
import importlib.util
import json
import logging
import logging.handlers
import os
import pickle
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import ray
from mlflow import MlflowClient

from cdm.config import load_config
from cdm.io.images import read_image
from sweeps import run
from sweeps.execute import driver, local_cluster, stopping
from sweeps.execute.claim import ClaimError, claim, claims_folder
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from sweeps.store import tracking
from sweeps.store.files import StoreError, check_name, check_resume_trust, private_folder, record_digest, sweep_location
from sweeps.store.sweep_run import SweepRun
from sweeps.store.trial_run import TrialRun

SPEC = "name: s\ngrid: {priors.point_size: [0.04]}\n"
OTHER_UID = 4242
"""A uid that is not this process's (the tests run as root, which may chown to it)."""


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
    return err


@pytest.fixture
def in_tmp(tmp_path, monkeypatch) -> Path:
    """A working folder holding ``spec.yaml`` (spec ``s``), with this user's state folder inside it."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    (tmp_path / "spec.yaml").write_text(SPEC)
    return tmp_path


def _argv(tmp: Path, *extra: str) -> list[str]:
    return ["spec.yaml", "--smoke", "--out", "results", "--tracking-uri", f"sqlite:///{tmp}/m.db", *extra]


# --- item 1: nothing follows a link it did not make -------------------------------------------------

@pytest.mark.parametrize("plant", ["symlink", "hardlink"])
def test_a_planted_lock_link_is_refused_and_its_target_untouched(in_tmp, capsys, plant):
    victim = in_tmp / "victim.txt"
    victim.write_text("precious\n")
    (in_tmp / "results" / "s").mkdir(parents=True)
    lock = in_tmp / "results" / "s" / ".smoke.lock"
    os.symlink(victim, lock) if plant == "symlink" else os.link(victim, lock)
    assert run.main(_argv(in_tmp)) == 2
    err = _one_error_line(capsys)
    assert str(lock) in err and ("symbolic link" if plant == "symlink" else "2 links") in err, err
    assert victim.read_text() == "precious\n" and os.path.lexists(lock)
    assert not (in_tmp / "m.db").exists() and not ray.is_initialized()


def test_a_foreign_or_linked_claims_folder_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    victim_dir = tmp_path / "elsewhere"
    victim_dir.mkdir()
    claims_folder().symlink_to(victim_dir)
    with pytest.raises(ClaimError, match="a link or a file where this user's private folder should be"):
        claim("s3://bucket/results/s/smoke")
    assert list(victim_dir.iterdir()) == []
    claims_folder().unlink()
    claims_folder().mkdir(mode=0o777)
    os.chmod(claims_folder(), 0o777)  # as another user would leave it for everyone
    with pytest.raises(ClaimError, match="mode 777"):
        claim("s3://bucket/results/s/smoke")
    os.chmod(claims_folder(), 0o700)
    os.chown(claims_folder(), OTHER_UID, -1)
    with pytest.raises(ClaimError, match=f"owned by uid {OTHER_UID}"):
        claim("s3://bucket/results/s/smoke")


def test_the_claims_folder_is_made_private(tmp_path, monkeypatch):
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    held = claim("s3://bucket/results/s/smoke")
    info = claims_folder().stat()
    assert (info.st_mode & 0o777, info.st_uid) == (0o700, os.getuid())
    held.release()
    assert private_folder(claims_folder()) == claims_folder()  # kept, and still accepted


def test_a_planted_state_file_link_is_not_written_through(in_tmp):
    victim = in_tmp / "victim.txt"
    victim.write_text("precious\n")
    folder = in_tmp / "results" / "s" / "smoke"
    folder.mkdir(parents=True)
    (folder / "sweep.json").symlink_to(victim)
    with pytest.raises(OSError):
        driver._write_new(folder / "sweep.json", "{}")
    assert victim.read_text() == "precious\n"


@pytest.mark.parametrize("plant", ["symlink", "hardlink"])
def test_results_files_are_never_written_through_a_planted_link(tmp_path, plant):
    from sweeps.compare.outcomes import TrialOutcome
    from sweeps.compare.table import build_table

    table = build_table([TrialOutcome("a · seed 0", "a", "ok", {"eval/f1": 0.5})], "eval/f1", "max", "t")
    clean = tmp_path / "clean"
    md, csv_file = table.write(clean)
    assert md.read_text() == table.markdown() and "0.5" in csv_file.read_text().splitlines()[1].split(",")
    table.write(clean)  # written again in place (a resumed sweep): one name, its own file
    folder = tmp_path / "sweep"
    folder.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (folder / "results.md").symlink_to(victim) if plant == "symlink" else os.link(victim, folder / "results.md")
    with pytest.raises(StoreError, match="symbolic link where this command" if plant == "symlink" else "2 links"):
        table.write(folder)
    assert victim.read_text() == "precious\n"



@pytest.mark.parametrize("kind", ["settle.json", "plot", "viewer"])
def test_settle_json_plots_and_the_viewer_are_never_written_through_a_planted_link(tmp_path, kind):
    """What a sequential sweep and the report write beside the table, under --trust-storage too: the
    writers take no flag, so nothing can follow a link planted at their names."""
    import numpy as np

    from sweeps.compare.gallery import grid_png, viewer_html
    from sweeps.execute.settle import UntilSettled
    from sweeps.plan.spec import Spec
    from sweeps.plan.trials import expand

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    clouds = {"o1": {"a": np.zeros((8, 3))}}
    plan = expand(Spec.model_validate({"name": "t", "cells": [{"label": "a"}]}), "smoke")
    write = {"settle.json": lambda path: UntilSettled(plan).write_json(path, {}),
             "plot": lambda path: grid_png(clouds, ["a"], "t", path, f1_thresholds=0.01),
             "viewer": lambda path: viewer_html(clouds, ["a"], "t", path)}[kind]
    clean = tmp_path / "clean" / "out"
    clean.parent.mkdir()
    write(clean)
    assert clean.stat().st_size > 0
    planted = tmp_path / "planted"
    planted.symlink_to(victim)
    with pytest.raises(StoreError, match="symbolic link where this command writes"):
        write(planted)
    assert victim.read_text() == "precious\n"


# --- item 2: no unpickling of what someone else could have written ----------------------------------

class _Planted:
    """A pickle that runs code when loaded: it makes the folder ``marker``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.mkdir, (str(self.marker),)


def _stopped_sweep(tmp: Path, parent: bool = True) -> Path:
    """A local sweep folder as a stopped sweep leaves it (its ``sweep.json``), this user's, mode 755; with
    ``parent``, its FINISHED parent run in ``<tmp>/m.db``, else a run id no store holds."""
    folder = tmp / "results" / "s" / "smoke"
    (folder / "trial_0").mkdir(parents=True)
    run_id = "0" * 32
    if parent:
        sweep = SweepRun.start(f"sqlite:///{tmp}/m.db", "s", "s · smoke", tags={}, params={})
        sweep.end("FINISHED")
        run_id = sweep.run_id
    state = {"spec": load_spec(tmp / "spec.yaml").model_dump(mode="json"), "sets": {}, "profile": "smoke",
             "tracking_uri": f"sqlite:///{tmp}/m.db", "parent_run_id": run_id}
    (folder / "sweep.json").write_text(json.dumps(state))
    return folder


@pytest.mark.parametrize("how", ["writable", "foreign", "symlink"])
def test_resume_refuses_tune_state_others_could_have_written(in_tmp, capsys, how):
    folder = _stopped_sweep(in_tmp)
    marker = in_tmp / "pwned"
    planted = folder / "tuner.pkl"
    if how == "symlink":
        (in_tmp / "outside.pkl").write_bytes(pickle.dumps(_Planted(marker)))
        planted.symlink_to(in_tmp / "outside.pkl")
    else:
        planted.write_bytes(pickle.dumps(_Planted(marker)))
        if how == "writable":
            os.chmod(planted, 0o666)
        else:
            os.chown(planted, OTHER_UID, -1)
    capsys.readouterr()  # MLflow's lines from making the parent run
    assert run.main(_argv(in_tmp, "--resume")) == 2
    err = _one_error_line(capsys)
    assert str(planted) in err and "--trust-storage" in err, err
    assert not marker.exists() and not ray.is_initialized()
    parent = json.loads((folder / "sweep.json").read_text())["parent_run_id"]
    assert MlflowClient(f"sqlite:///{in_tmp}/m.db").get_run(parent).info.status == "FINISHED"  # left as it was
    assert not (in_tmp / "results" / "s" / ".smoke.lock").exists()  # the claim was released


def test_a_folder_of_this_user_alone_is_trusted(in_tmp):
    folder = _stopped_sweep(in_tmp)
    (folder / "tuner.pkl").write_bytes(pickle.dumps({"state": 1}))
    check_resume_trust(str(folder))
    os.chmod(folder / "trial_0", 0o775)  # a group-writable folder could have had tuner.pkl swapped
    with pytest.raises(StoreError, match="trial_0 can be written by others"):
        check_resume_trust(str(folder))


def test_object_store_state_is_trusted_only_as_its_last_driver_left_it(in_tmp):
    folder = _stopped_sweep(in_tmp)
    (folder / "tuner.pkl").write_bytes(pickle.dumps({"state": 1}))
    (folder / "trial_0" / "checkpoint_000001").mkdir()
    (folder / "trial_0" / "checkpoint_000001" / "model.pt").write_bytes(b"weights")
    uri = f"file://{folder}"
    with pytest.raises(StoreError, match="no digest of .* was recorded .*--trust-storage"):
        check_resume_trust(uri)
    record_digest(uri)
    check_resume_trust(uri)
    (folder / "trial_0" / "checkpoint_000001" / "model.pt").write_bytes(b"newer weights")  # torch, weights only
    check_resume_trust(uri)
    (folder / "tuner.pkl").write_bytes(pickle.dumps(_Planted(in_tmp / "pwned")))
    with pytest.raises(StoreError, match=r"tuner.pkl differs from what this user's last driver left \(1 file"):
        check_resume_trust(uri)
    assert not (in_tmp / "pwned").exists()
    digests = in_tmp / "state" / "cdm" / "sweep-digests"
    assert digests.stat().st_mode & 0o777 == 0o700


# --- item 4: every path component a user names is checked --------------------------------------------

@pytest.mark.parametrize("name,needle", [("../../../x", "not a plain name"), ("..", "not a plain name"),
                                         ("a/b", "not a plain name"), (".hidden", "not a plain name"),
                                         ("x" * 101, "101 characters"), ("", "not a plain name")])
def test_bad_names_are_refused(name, needle):
    with pytest.raises(StoreError, match=needle):
        check_name(name, "profile")
    check_name("x" * 100, "profile")
    check_name("paper_v2.1-b", "profile")


def test_a_profile_path_is_refused_and_nothing_is_written_outside_storage(in_tmp, capsys):
    argv = _argv(in_tmp, "--profile", "../../../x")
    argv.remove("--smoke")
    assert run.main(argv) == 2
    assert "profile '../../../x': not a plain name" in _one_error_line(capsys)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["spec.yaml"]


def test_a_300_character_spec_name_is_refused_leaving_no_folder(in_tmp, capsys):
    (in_tmp / "spec.yaml").write_text(SPEC.replace("name: s", "name: " + "n" * 300))
    assert run.main(_argv(in_tmp)) == 2
    assert "300 characters; a name may have at most 100" in _one_error_line(capsys)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["spec.yaml"]


@pytest.mark.parametrize("target", ["dangling", "folder"])
def test_a_link_at_the_sweep_folder_is_refused(in_tmp, capsys, target):
    elsewhere = in_tmp / "elsewhere"
    if target == "folder":
        elsewhere.mkdir()
    (in_tmp / "results" / "s").mkdir(parents=True)
    (in_tmp / "results" / "s" / "smoke").symlink_to(elsewhere)
    assert run.main(_argv(in_tmp)) == 2
    assert "results/s/smoke is a symbolic link" in _one_error_line(capsys)
    assert (not elsewhere.exists()) if target == "dangling" else list(elsewhere.iterdir()) == []


def test_sweep_location_stays_under_storage(tmp_path):
    assert sweep_location(str(tmp_path), "s", "smoke") == f"{tmp_path.resolve()}/s/smoke"
    assert sweep_location("s3://b/r/", "s", "smoke") == "s3://b/r/s/smoke"
    with pytest.raises(StoreError):
        sweep_location(str(tmp_path), "s", "../smoke")


# --- item 3: leftover processes are ended only when provably ours -----------------------------------

def _holding(session: Path, title: str) -> subprocess.Popen:
    """A process (command line ``title`` …) holding a file open in ``session``; prints once it does."""
    code = "import os, time; f = open(os.environ['LOG'], 'a'); print('open', flush=True); time.sleep(60)"
    proc = subprocess.Popen([sys.executable, "-c", code, title], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "LOG": str(session / "log")})  # not on its command line
    assert proc.stdout.readline().strip() == "open"
    return proc


def _dead_pid() -> int:
    gone = subprocess.Popen(["true"])
    gone.wait()
    return gone.pid


def test_a_planted_session_record_ends_no_unrelated_process(tmp_path, monkeypatch):
    records = tmp_path / "records"
    monkeypatch.setattr(local_cluster, "SESSION_RECORDS", records)
    session = tmp_path / "session_2026-01-01_00-00-00_1"
    session.mkdir()
    victim = _holding(session, "an unrelated server")
    ray_worker = _holding(session, f"--session-dir={session}")
    try:
        private_folder(records)
        (records / "1.json").write_text(json.dumps({"pid": _dead_pid(), "session_dir": str(session)}))
        assert local_cluster.reap_stale_sessions() == [ray_worker.pid]
        assert ray_worker.wait(10) == -signal.SIGKILL and victim.poll() is None  # the victim is alive
        (records / "2.json").write_text(json.dumps({"pid": _dead_pid(), "session_dir": str(session)}))
        os.chmod(records, 0o777)  # a records folder anyone could have written into
        with pytest.raises(StoreError, match="mode 777"):
            local_cluster.reap_stale_sessions()
        assert victim.poll() is None and (records / "2.json").exists()
    finally:
        for proc in (victim, ray_worker):
            proc.kill()
            proc.wait()


# --- item 6: checked before Ray starts, in one line, exit 2 -------------------------------------------

class _HealthOnly(http.server.BaseHTTPRequestHandler):
    """Any web server: ``/health`` says OK, everything else is 404."""

    def do_GET(self):  # noqa: N802 (http.server's name)
        self.send_response(200 if self.path == "/health" else 404)
        self.end_headers()
        self.wfile.write(b"OK")

    def log_message(self, *args):
        pass


def test_a_server_answering_health_but_not_mlflow_is_refused(in_tmp, capsys):
    server = http.server.HTTPServer(("127.0.0.1", 0), _HealthOnly)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        argv = _argv(in_tmp)[:-2] + ["--tracking-uri", f"http://127.0.0.1:{server.server_port}"]
        assert run.main(argv) == 2
    finally:
        server.shutdown()
    assert "answers /health but not MLflow's API (experiments/search: HTTP Error 404" in _one_error_line(capsys)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["spec.yaml"] and not ray.is_initialized()


@pytest.mark.parametrize("uri,driver", [("postgresql://u@127.0.0.1/mlflow", "psycopg2"),
                                        ("mysql+nosuchdriver://u@127.0.0.1/mlflow", "nosuchdriver")])
def test_a_database_uri_without_its_driver_is_refused(in_tmp, capsys, uri, driver):
    assert importlib.util.find_spec(driver) is None
    assert run.main(_argv(in_tmp)[:-2] + ["--tracking-uri", uri]) == 2
    assert f"its database driver {driver!r} is not installed" in _one_error_line(capsys)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["spec.yaml"]


def test_resume_against_a_store_without_the_parent_run_creates_nothing(in_tmp, capsys):
    folder = _stopped_sweep(in_tmp, parent=False)
    assert run.main(_argv(in_tmp, "--resume")[:-3] + ["--resume"]) == 2  # the store named in sweep.json
    assert f"the MLflow store sqlite:///{in_tmp}/m.db does not exist" in _one_error_line(capsys)
    assert not (in_tmp / "m.db").exists() and sorted(p.name for p in folder.iterdir()) == ["sweep.json", "trial_0"]
    other = SweepRun.start(f"sqlite:///{in_tmp}/other.db", "exp", "exp", tags={}, params={})
    other.end("FINISHED")
    capsys.readouterr()
    assert run.main(_argv(in_tmp, "--resume")[:-3] + ["--resume", "--tracking-uri", other.uri]) == 2
    assert f"has no parent run {'0' * 32}" in _one_error_line(capsys)
    assert not ray.is_initialized()


@pytest.mark.parametrize(
    "value,needle",
    [
        ("[" * 50_000 + "]" * 50_000, "100016 characters; a --set may have at most 4096"),
        ("[" + ",".join(["a"] * 20_000) + "]", "40017 characters"),
        ("[" * 17 + "a" + "]" * 17, "brackets nested 17 deep"),
    ],
)
def test_a_huge_or_deep_set_value_is_refused_at_once(in_tmp, capsys, value, needle):
    started = time.perf_counter()
    assert run.main(_argv(in_tmp, "--set", f"data.categories={value}")) == 2
    err = _one_error_line(capsys)
    assert needle in err and len(err) < 300 and time.perf_counter() - started < 5, err
    assert sorted(p.name for p in in_tmp.iterdir()) == ["spec.yaml"]


# --- item 7: decoded-image caps ----------------------------------------------------------------------

def _png_header(width: int, height: int, bit_depth: int, colour: int) -> bytes:
    """A PNG whose header claims ``width``×``height`` pixels, with one tiny (truncated) data chunk: what
    a bomb looks like before it is decoded."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


@pytest.mark.parametrize("side,depth,colour,flags,needle", [
    (32768, 1, 0, cv2.IMREAD_UNCHANGED, "is over 178956970 pixels"),  # PIL's own cap
    (12000, 16, 2, cv2.IMREAD_UNCHANGED, r"is 12000×12000 pixels \(decoding takes 1.1 GiB\)"),
    (9000, 8, 0, cv2.IMREAD_COLOR, r"is 9000×9000 pixels \(decoding takes 0.2 GiB\)")])
def test_an_image_bomb_is_refused_from_its_header(tmp_path, side, depth, colour, flags, needle):
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(_png_header(side, side, depth, colour))
    assert bomb.stat().st_size < 200
    with pytest.raises(ValueError, match=rf"data.root: .*bomb.png {needle}; an image may have at most 67108864 pixels"):
        read_image(bomb, flags, "data.root")


def test_reconstruct_refuses_an_image_bomb_and_reads_a_real_image_as_opencv_does(tmp_path):
    from cdm.__main__ import _load_image

    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(_png_header(10000, 10000, 16, 6))
    with pytest.raises(ValueError, match=r"--image: .*10000×10000 pixels \(decoding takes 0.7 GiB\)"):
        _load_image(bomb, 64)
    picture = tmp_path / "ok.png"
    pixels = np.random.default_rng(0).integers(0, 65535, (40, 50, 4), dtype=np.uint16)
    cv2.imwrite(str(picture), pixels)
    np.testing.assert_array_equal(read_image(picture, cv2.IMREAD_UNCHANGED, "--image"), pixels)
    assert read_image(tmp_path / "missing.png", cv2.IMREAD_COLOR, "--image") is None
    (tmp_path / "text.png").write_text("not an image")
    assert read_image(tmp_path / "text.png", cv2.IMREAD_COLOR, "--image") is None


# --- item 5 (and 6: a store locked at start): a busy SQLite store is waited on -----------------------

def _lock_store(db: Path, hold_s: float) -> subprocess.Popen:
    """Another writer holding ``db``'s write lock for ``hold_s`` seconds; prints once it holds it."""
    code = (
        "import sqlite3, sys, time; c = sqlite3.connect(sys.argv[1], isolation_level=None); "
        "c.execute('BEGIN EXCLUSIVE'); print('locked', flush=True); time.sleep(float(sys.argv[2])); "
        "c.execute('ROLLBACK')"
    )
    holder = subprocess.Popen([sys.executable, "-c", code, str(db), str(hold_s)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    return holder


@pytest.mark.slow
def test_a_trial_logs_through_a_store_another_writer_holds_for_longer_than_sqlites_5_s(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "cell · seed 0", {}, load_config(None))
    holder = _lock_store(tmp_path / "mlflow.db", 7.0)
    started = time.perf_counter()
    try:
        trial.on_step(10, {"train/loss": 0.5})  # "database is locked" after 5 s without the busy timeout
    finally:
        holder.wait()
    assert time.perf_counter() - started > 5.0
    assert [m.value for m in MlflowClient(uri).get_metric_history(trial.run_id, "train/loss")] == [0.5]


@pytest.mark.slow
class _LockedThenFree:
    """An MLflow call that fails with "database is locked" ``times`` times (as when SQLite skips its busy
    wait to avoid a deadlock), then answers; counts its calls."""

    def __init__(self, times: int, message: str = "(sqlite3.OperationalError) database is locked"):
        self.times, self.message, self.calls = times, message, 0

    def __call__(self, value: int) -> int:
        from mlflow.exceptions import MlflowException

        self.calls += 1
        if self.calls <= self.times:
            raise MlflowException(self.message, error_code="TEMPORARILY_UNAVAILABLE")
        return value


def test_a_dataset_two_trials_insert_at_once_is_retried_and_the_retry_links_the_stored_row(tmp_path):
    from mlflow.entities import Dataset, DatasetInput

    race = _LockedThenFree(1, "(sqlite3.IntegrityError) UNIQUE constraint failed: datasets.experiment_id, "
                              "datasets.name, datasets.digest")
    assert tracking.retry_when_busy(race, 7) == 7 and race.calls == 2
    # What the retry meets in a real store: the other trial's row, which it links instead of inserting.
    client = tracking.PatientClient(f"sqlite:///{tmp_path}/m.db")
    experiment = client.create_experiment("race")
    runs = [client.create_run(experiment).info.run_id for _ in range(2)]
    for run_id in runs:
        client.log_inputs(run_id, datasets=[DatasetInput(Dataset("procedural quick eval", "e1", "code", "{}"))])
    used = [client.get_run(r).inputs.dataset_inputs[0].dataset for r in runs]
    assert [(d.name, d.digest) for d in used] == [("procedural quick eval", "e1")] * 2


def test_an_mlflow_call_refused_as_locked_is_retried_with_back_off_until_the_wait_ends(tmp_path, monkeypatch):
    from mlflow.exceptions import MlflowException

    call = _LockedThenFree(3)
    started = time.perf_counter()
    assert tracking.retry_when_busy(call, 7) == 7 and call.calls == 4
    assert time.perf_counter() - started >= 0.1 + 0.2 + 0.4  # the pauses between the four calls
    other = _LockedThenFree(1, "RESOURCE_DOES_NOT_EXIST: run 0 not found")
    with pytest.raises(MlflowException, match="not found"):
        tracking.retry_when_busy(other, 7)
    assert other.calls == 1  # other errors are not waited on
    monkeypatch.setattr(tracking, "BUSY_TIMEOUT_S", 0.5)
    stuck = _LockedThenFree(100)
    with pytest.raises(MlflowException, match="database is locked"):
        tracking.retry_when_busy(stuck, 7)
    assert stuck.calls == 3  # after 0.1 + 0.2 s; a third pause of 0.4 s would pass the 0.5 s wait
    client = tracking.PatientClient(f"sqlite:///{tmp_path}/m.db")
    assert client.tracking_uri == f"sqlite:///{tmp_path}/m.db"
    assert [e.name for e in client.search_experiments()] == ["Default"]
    tracking.wait_when_busy()  # MLflow's traceback of each retried "database is locked" is not printed
    mlflow_db = logging.getLogger("mlflow.store.db.utils")
    seen = logging.handlers.BufferingHandler(10)
    mlflow_db.addHandler(seen)
    try:
        for error in ("(sqlite3.OperationalError) database is locked", "(sqlite3.OperationalError) disk I/O error"):
            mlflow_db.error("SQLAlchemy database error. The following exception is caught.\n%s", error)
    finally:
        mlflow_db.removeHandler(seen)
    assert [r.getMessage().split("\n")[1] for r in seen.buffer] == ["(sqlite3.OperationalError) disk I/O error"]


def test_a_store_locked_at_start_is_waited_on_then_refused_in_one_line(in_tmp, capsys, monkeypatch):
    SweepRun.start(f"sqlite:///{in_tmp}/m.db", "other", "other", tags={}, params={}).end("FINISHED")
    monkeypatch.setattr(tracking, "BUSY_TIMEOUT_S", 2.0)
    capsys.readouterr()
    holder = _lock_store(in_tmp / "m.db", 30.0)
    try:
        started = time.perf_counter()
        assert run.main(_argv(in_tmp)) == 2
        assert 2.0 <= time.perf_counter() - started < 20.0
    finally:
        holder.kill()
        holder.wait()
    assert "database is locked by another writer for 2 s" in _one_error_line(capsys)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["m.db", "spec.yaml"]
    assert not ray.is_initialized()


# --- item 8: the smaller items -----------------------------------------------------------------------

def test_the_resume_hint_keeps_the_storage():
    assert stopping.resume_command(Path("sweeps/s.yaml"), "smoke", "/mnt/my results") == (
        "python sweeps/run.py sweeps/s.yaml --profile smoke --out '/mnt/my results' --resume")


def test_interrupted_children_are_closed_as_killed_and_reopened_by_resume(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    running = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, load_config(None))
    done = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t1", "b · seed 0", {}, load_config(None))
    sweep.close_trial("t1", "b · seed 0", "FINISHED")
    assert stopping.kill_running_children(sweep) == 1
    client = MlflowClient(uri)
    assert [client.get_run(r.run_id).info.status for r in (running, done)] == ["KILLED", "FINISHED"]
    again = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, load_config(None))
    assert again.run_id == running.run_id and client.get_run(running.run_id).info.status == "RUNNING"


def test_rays_token_file_is_made_private(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    local_cluster.private_token()  # none yet: nothing to do
    (tmp_path / ".ray").mkdir()
    token = tmp_path / ".ray" / "auth_token"
    token.write_text("secret")
    token.chmod(0o644)
    local_cluster.private_token()
    assert token.stat().st_mode & 0o777 == 0o600


# --- item 6: a full disk is said as such ---------------------------------------------------------------

def test_a_full_disk_is_recognised_from_python_and_from_torch():
    import torch

    with pytest.raises(OSError) as full:
        with open("/dev/full", "wb") as out:  # the kernel's always-full device
            out.write(b"x" * 65536)
    with pytest.raises(RuntimeError) as torch_full:
        torch.save(torch.zeros(100_000), "/dev/full")  # torch says only "unexpected pos"
    assert stopping.no_space_left(full.value) and stopping.no_space_left(torch_full.value)
    try:
        raise RuntimeError("trial failed") from full.value  # as Ray wraps a worker's error
    except RuntimeError as wrapped:
        assert stopping.no_space_left(wrapped)
    assert not stopping.no_space_left(ValueError("data.root: cannot read"))


@contextlib.contextmanager
def small_disk(folder: Path, size: str) -> Iterator[Path]:
    """``folder`` as a fresh tmpfs of ``size`` (``mount -o size=…``); the test is skipped where mounting is not
    allowed."""
    folder.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small disk here: {mounted.stderr.decode().strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def test_a_disk_too_small_for_the_shared_views_is_refused_before_anything_is_made(in_tmp, capsys):
    from sweeps.execute.precompute import shared_bytes

    plan = expand(load_spec(in_tmp / "spec.yaml"), "smoke")
    need = shared_bytes(plan)
    assert 2 * 2**20 < need < 3 * 2**20  # the smoke profile's views and evaluation set: 2.1 MiB
    with small_disk(in_tmp / "disk", "2m") as disk:
        argv = _argv(in_tmp)
        argv[argv.index("results")] = str(disk)
        assert run.main(argv) == 2
        err = _one_error_line(capsys)
        assert f"need {need / 2**20:.1f} MiB but its disk has 2.0 MiB free; free space" in err, err
        assert list(disk.iterdir()) == []  # no lock, no sweep.json, no shared folder
    assert not (in_tmp / "m.db").exists() and not ray.is_initialized()


def test_a_start_that_ran_no_trial_is_discarded_whole(tmp_path):
    for sweep in (tmp_path / "local" / "s" / "smoke", tmp_path / "uri" / "s" / "smoke"):
        (sweep / "shared").mkdir(parents=True)
        (sweep / "sweep.json").write_text("{}")
    stopping.discard_start(str(tmp_path / "local" / "s" / "smoke"))
    stopping.discard_start(f"file://{tmp_path}/uri/s/smoke")
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == ["local", "local/s", "uri", "uri/s"]


def test_the_encoder_weights_refusal_never_advises_weights_only_false(tmp_path):
    import argparse

    import torch

    from cdm.model.encoder import load_msn_state_dict

    torch.save({"target_encoder": argparse.Namespace(code=1)}, tmp_path / "objects.pth")
    (tmp_path / "garbage.pth").write_bytes(b"not a torch file")
    for name, reason in (
        ("objects.pth", "could run code from the file"),
        ("garbage.pth", "not in torch's file format"),
    ):
        with pytest.raises(ValueError, match=reason) as refused:
            load_msn_state_dict(tmp_path / name)
        assert "weights_only" not in str(refused.value)


def test_a_bad_set_value_is_labelled_as_set_not_as_the_profile(in_tmp, capsys):
    assert run.main(_argv(in_tmp, "--set", "data.num_points=3")) == 2
    err = _one_error_line(capsys)
    assert err.startswith("error: --set: data.num_points") and "profile" not in err.split(":")[1], err


def test_a_data_set_name_that_leaves_its_root_is_refused(in_tmp, capsys):
    # Data set names are matched against the categories the data set has (its folders), never joined blindly.
    assert run.main(_argv(in_tmp, "--set", "data.categories=[chair, ../../etc]", "--dry-run")) == 2
    assert "data.categories: ['../../etc'] not in the procedural data set" in _one_error_line(capsys)
    assert sorted(p.name for p in in_tmp.iterdir()) == ["spec.yaml"]


def test_only_rays_note_that_token_auth_is_on_is_dropped():
    import logging

    from sweeps.execute.local_cluster import DeliberateTokenNote

    def record(message: str) -> logging.LogRecord:
        return logging.LogRecord("ray", logging.WARNING, __file__, 1, message, None, None)

    drop = DeliberateTokenNote()
    assert not drop.filter(record("Token authentication is enabled for this Ray cluster. Set RAY_AUTH_MODE=disabled …"))
    assert drop.filter(record("Token authentication is not enabled. Anyone with network access to the cluster …"))
