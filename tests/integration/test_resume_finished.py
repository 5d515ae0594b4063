"""A trial that finished just before its driver was killed, while Tune's last snapshot still lists it as
running, is recognised on ``--resume`` from its own MLflow record: not trained again, ``final/…`` once.

The lagging snapshot is made exactly: Tune's experiment state is copied while the trial runs and put
back after the sweep has finished, which is what a kill in the second between the trial's end and
Tune's next snapshot leaves behind. Real Ray (a local cluster the driver joins), MLflow and files.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow import MlflowClient

from sweeps import run

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def test_finished_trial_missing_from_tunes_snapshot_is_not_rerun(cluster, tmp_path, capfd):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        "name: late\ngrid: {priors.point_size: [0.04]}\nprofiles: {smoke: {budget: {steps: 20, eval_every: 10}}}\n"
    )
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    argv = [str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri]
    folder = tmp_path / "results" / "late" / "smoke"
    driver = subprocess.Popen([sys.executable, str(ROOT / "sweeps" / "run.py"), *argv, "--address", cluster],
                              cwd=tmp_path, stdout=(tmp_path / "driver.log").open("w"), stderr=subprocess.STDOUT)
    snapshot: dict[Path, bytes] = {}
    deadline = time.monotonic() + 240
    while driver.poll() is None and not snapshot:
        assert time.monotonic() < deadline, (tmp_path / "driver.log").read_text()[-3000:]
        if list(folder.glob("trial_*/checkpoint_000000")):  # running, and Tune has written its state
            snapshot = {p: p.read_bytes() for p in folder.glob("experiment_state-*.json")}
        time.sleep(0.1)
    assert driver.wait(timeout=300) == 0, (tmp_path / "driver.log").read_text()[-3000:]
    assert snapshot, "the trial finished before its first checkpoint was seen"
    for path, data in snapshot.items():
        path.write_bytes(data)
    capfd.readouterr()

    assert run.main([*argv, "--resume"]) == 0
    out = capfd.readouterr().out
    assert "already finished before the driver stopped" in out
    assert "resuming from" not in out and "step 5/20" not in out  # no training at all
    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name("late").experiment_id
    children = [r for r in client.search_runs([experiment]) if "mlflow.parentRunId" in r.data.tags]
    assert len(children) == 1 and children[0].info.status == "FINISHED"
    assert [m.step for m in client.get_metric_history(children[0].info.run_id, "final/f1")] == [20]
    assert sorted(m.step for m in client.get_metric_history(children[0].info.run_id, "train/loss")) == [5, 10, 15, 20]
    table = out[out.index("late — profile smoke"):]
    assert "point_size=0.04" in table and " 1/1 " in table
