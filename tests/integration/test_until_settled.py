"""Seeds until settled, end to end: a real local Ray cluster, the Tune searcher, a real MLflow SQLite store.

Two planted cells beside a reference: ``null`` differs only in how many clouds its evaluation saves
(``eval.save_clouds``, which cannot change a score), ``large`` scores F1 with a 25× looser threshold
(``eval.f1_threshold`` 0.25: nearly every point counts, a large effect no seed can undo). The null cell's
differences are exactly 0 at every seed, so without a margin it stays open and runs to ``max``; the
large effect settles at the first look. A second test kills the driver after round 1 and resumes it.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
from mlflow import MlflowClient

from sweeps import report, run

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]

SPEC = """
name: {name}
cells:
  - {{label: reference}}
  - {{label: "null", set: {{eval.save_clouds: 1}}}}
{large}seeds: {{min: {min}, max: {max}, until: settled}}
resources: {{max_concurrent_trials: 2}}
profiles: {{smoke: {{budget: {{steps: {steps}, eval_every: 10}}}}}}
"""
LARGE = "  - {label: large, set: {eval.f1_threshold: 0.25}}\n"


def _sweep(tmp_path: Path, name: str, large: bool, low: int, high: int, steps: int = 10) -> tuple[list[str], str]:
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC.format(name=name, large=LARGE if large else "", min=low, max=high, steps=steps))
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    return [str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri], uri


def _children(uri: str, experiment: str) -> tuple[MlflowClient, list, list]:
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return client, [], []
    runs = client.search_runs([exp.experiment_id])
    return (
        client,
        [r for r in runs if r.data.tags.get("kind") == "sweep"],
        [r for r in runs if "mlflow.parentRunId" in r.data.tags],
    )


def _settle(client: MlflowClient, parent_id: str, tmp_path: Path) -> dict:
    return json.loads(Path(client.download_artifacts(parent_id, "settle.json", str(tmp_path))).read_text())


def test_a_planted_null_and_a_large_effect_are_told_apart_by_their_seeds(cluster, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # report writes its folder under ./results
    argv, uri = _sweep(tmp_path, "settle", large=True, low=4, high=5)
    t0 = time.perf_counter()
    assert run.main(argv) == 0
    wall = time.perf_counter() - t0
    out = capsys.readouterr().out
    client, parents, children = _children(uri, "settle")
    labels = Counter(c.info.run_name for c in children)
    # Round 1: every cell at 4 seeds (at 3, ten smoke steps leave the large cell's seeds x objects interval
    # holding 0 on some kernels); round 2: the open null cell and the reference at seed 4; no more.
    assert labels == Counter({f"{cell} · seed {s}": 1 for cell, seeds in (("reference", 5), ("null", 5), ("large", 4))
                              for s in range(seeds)})
    assert all(c.info.status == "FINISHED" for c in children)
    cells = _settle(client, parents[0].info.run_id, tmp_path)["cells"]
    assert set(cells) == {"null", "large"}
    assert (cells["large"]["seeds"], cells["large"]["verdict"], cells["large"]["reason"]) == (4, "better", "settled")
    assert (cells["null"]["seeds"], cells["null"]["verdict"], cells["null"]["reason"]) == (5, "open", "max")
    assert cells["null"]["interval"]["low"] == cells["null"]["interval"]["high"] == 0.0  # the same scores at every seed
    assert cells["large"]["interval"]["low"] > 0.0 and cells["large"]["interval"]["covers"] == "seeds and objects"
    assert "round 2 of ≤2" in out and "(14/≤15 trials done)" in out
    table = out[out.index("settle — profile smoke"):]
    assert "better, settled after 4 seeds" in table and "open at 5 seeds" in table
    description = parents[0].data.tags["mlflow.note.content"]  # the parent run's page says it too
    assert "better, settled after 4 seeds" in description and "open at 5 seeds" in description
    # Rebuilt from MLflow alone: the same stops, and no row for the seed the large cell never needed.
    assert report.main(["settle", "--tracking-uri", uri]) == 0
    rebuilt = capsys.readouterr().out
    assert "better, settled after 4 seeds" in rebuilt and "open at 5 seeds" in rebuilt
    assert re.search(r"^large\b.*\s4/4\s", rebuilt, re.M) and re.search(r"^null\b.*\s5/5\s", rebuilt, re.M), rebuilt
    print(f"\nnull vs large, 14 trials until settled: {wall:.1f} s wall")


def test_a_driver_killed_after_round_1_resumes_without_running_a_seed_twice(cluster, tmp_path, capfd):
    argv, uri = _sweep(tmp_path, "again", large=False, low=2, high=3, steps=40)  # round 2 still runs when killed
    log = (tmp_path / "driver.log").open("w")
    driver = subprocess.Popen([sys.executable, str(ROOT / "sweeps" / "run.py"), *argv, "--address", cluster],
                              cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 300
    # Round 1 has finished once round 2 starts; killed then, Tune's last snapshot (one a second) holds
    # round 2's proposals, which the restored searcher must neither lose nor propose again.
    while (
        time.monotonic() < deadline
        and driver.poll() is None
        and "▶ started [null · seed 2]" not in (tmp_path / "driver.log").read_text()
    ):
        time.sleep(0.2)
    time.sleep(1.5)
    assert driver.poll() is None, (tmp_path / "driver.log").read_text()[-3000:]
    os.kill(driver.pid, signal.SIGKILL)
    driver.wait()
    _, _, children = _children(uri, "again")
    finished = [c for c in children if c.info.status == "FINISHED"]
    round_1 = {f"{cell} · seed {s}" for cell in ("reference", "null") for s in (0, 1)}
    assert {c.info.run_name for c in finished} >= round_1
    capfd.readouterr()

    assert run.main([*argv, "--resume"]) == 0
    out = capfd.readouterr().out
    for name in (c.info.run_name for c in finished):
        # Round 1 is in Tune's snapshot as done: not scheduled again. A round-2 seed that finished after the
        # last snapshot is scheduled again, and its trial must find its finished MLflow run and not train.
        if name in round_1:
            assert f"▶ started [{name}]" not in out
        assert f"[{name}] step " not in out
        assert f"▶ started [{name}]" not in out or f"[{name}] already finished before the driver stopped" in out
    assert "[null · seed 2] resuming from" in out or "▶ started [null · seed 2]" in out
    client, parents, children = _children(uri, "again")
    labels = Counter(c.info.run_name for c in children)
    assert labels == Counter(
        {f"{cell} · seed {s}": 1 for cell in ("reference", "null") for s in range(3)}
    )  # none twice, none lost
    assert all(c.info.status == "FINISHED" for c in children)
    assert len({c.data.tags["trial_id"] for c in children}) == 6
    cells = _settle(client, parents[0].info.run_id, tmp_path)["cells"]
    assert list(cells) == ["null"] and (cells["null"]["seeds"], cells["null"]["verdict"], cells["null"]["reason"]) == (
        3,
        "open",
        "max",
    )
    assert set(cells["null"]["interval"]) == {"mean", "low", "high", "objects", "covers"}
