"""``--resume`` retries an errored trial (issue 59): a trial whose process is killed more often than
``failure.max_retries`` lets Tune restart it ends failed; the next ``--resume`` retries it from its last
checkpoint, says so, counts the retry in the sweep folder, and the trial finishes. Real Ray (the module's local
cluster), MLflow and files; the fault is a SIGKILL of the trial's process, as the kernel's OOM killer sends."""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest
import ray.tune
from mlflow import MlflowClient

from sweeps import run
from sweeps.execute.local_cluster import descendants
from sweeps.execute.resume_retries import RECORD, refusing

pytestmark = [pytest.mark.ray, pytest.mark.slow]

TRIAL_TITLE = b"ray::ImplicitFunc"  # how Ray titles a Tune function trainable's actor process


def _trial_pids() -> list[int]:
    pids = []
    for pid in sorted(descendants(os.getpid())):  # the module's cluster is this process's
        try:
            if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(TRIAL_TITLE):
                pids.append(pid)
        except OSError:  # gone meanwhile
            continue
    return pids


def _kill_trials(times: int, stop: threading.Event) -> list[int]:
    """SIGKILL each new trial process as it appears, ``times`` processes in all (or until ``stop``)."""
    killed: list[int] = []
    while len(killed) < times and not stop.is_set():
        for pid in _trial_pids():
            if pid not in killed and len(killed) < times:
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
        time.sleep(0.1)
    return killed


def test_an_errored_trial_is_retried_on_resume_and_finishes(cluster, tmp_path, capfd):
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: flaky\ngrid: {priors.point_size: [0.04]}\nfailure: {max_retries: 1}\n"
                    "profiles: {smoke: {budget: {steps: 20, eval_every: 10}}}\n")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    argv = [str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri]
    folder = tmp_path / "results" / "flaky" / "smoke"
    label = "point_size=0.04 · seed 0"

    stop, killed = threading.Event(), []
    killer = threading.Thread(target=lambda: killed.extend(_kill_trials(2, stop)))  # its first run and Tune's retry
    killer.start()
    try:
        assert run.main(argv) == 1  # no trial finished
    finally:
        stop.set()
        killer.join()
    out = capfd.readouterr().out
    assert len(killed) == 2, out[-3000:]
    assert f"✗ failed [{label}]" in out and f"✓ finished [{label}]" not in out
    assert not (folder / RECORD).exists()

    assert run.main([*argv, "--resume"]) == 0
    out = capfd.readouterr().out
    assert f"--resume: retrying 1 errored trial(s) from their last checkpoint: {label} (retry 1 of 1)" in out
    assert f"✓ finished [{label}] at step 20" in out and "✗ failed" not in out
    spent = json.loads((folder / RECORD).read_text())
    assert list(spent.values()) == [1]

    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name("flaky").experiment_id
    children = [r for r in client.search_runs([experiment]) if "mlflow.parentRunId" in r.data.tags]
    assert len(children) == 1 and children[0].info.status == "FINISHED"
    assert children[0].data.tags["trial_id"] == next(iter(spent))
    assert max(m.step for m in client.get_metric_history(children[0].info.run_id, "train/loss")) == 20
    rows = list(csv.DictReader(io.StringIO((folder / "results.csv").read_text())))
    cell = next(r for r in rows if r["cell"] == "point_size=0.04")
    assert (cell["ok"], cell["failed"]) == ("1", "0")


def test_a_given_up_trial_requeued_with_a_retried_one_refuses_and_the_other_finishes(cluster, tmp_path):
    """Tune resumes every errored trial or none: the given-up one's trainable refuses, under the name Tune's
    restore checks (the sweep's trainable is ``run_trial`` whether or not it refuses anything)."""
    def report_or_fail(config: dict, setup: dict) -> None:  # local: Ray's workers get it by value
        if setup["fail"]:
            raise ValueError(f"trial {config['i']} fails on its first run")
        ray.tune.report({"score": float(config["i"])})

    def tuner(fail: bool, given_up: dict[str, str]):
        return ray.tune.with_parameters(refusing(report_or_fail, given_up), setup={"fail": fail})

    ray.tune.Tuner(tuner(True, {}), param_space={"i": ray.tune.grid_search([0, 1])},
                   run_config=ray.tune.RunConfig(name="two", storage_path=str(tmp_path), verbose=0)).fit()
    first = ray.tune.ExperimentAnalysis(str(tmp_path / "two"))
    assert sorted(t.status for t in first.trials) == ["ERROR", "ERROR"]
    by_i = {t.config["i"]: t.trial_id for t in first.trials}
    grid = ray.tune.Tuner.restore(str(tmp_path / "two"), trainable=tuner(False, {by_i[0]: "given up: test"}),
                                  resume_errored=True).fit()
    outcome = {r.config["i"]: r for r in grid}
    assert "RetriesSpent: given up: test" in str(outcome[0].error) and outcome[0].metrics.get("score") is None
    assert outcome[1].error is None and outcome[1].metrics["score"] == 1.0
