"""End-to-end sweeps on a real local Ray cluster, real Optuna and a real MLflow SQLite store.

One Ray session serves the whole module (start-up is the slow part on 2 CPUs); every sweep uses the
smoke profile, shrunk further by the test specs. The 2-cell grid runs once (:func:`e2e`): its test
reads it end to end, the re-run test re-trains one of its trials.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import ray
from mlflow import MlflowClient

from cdm.io.write import TEMP_NAME
from cdm.provenance import MACHINE_KEYS, machine_record
from sweeps import rerun, run
from sweeps.store.read import last_eval_files
from sweeps.store.trial_run import PACKAGES_FILE

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def _sweep(tmp_path: Path, body: str, *extra: str) -> tuple[list[str], str]:
    """Write the spec; the runner's argv (smoke profile, storage and MLflow under tmp_path) and MLflow URI."""
    spec = tmp_path / "spec.yaml"
    spec.write_text(body)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    argv = [str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri, *extra]
    return argv, uri


def _children(uri: str, experiment: str):
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return client, [], []
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if r.data.tags.get("kind") == "sweep"]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    return client, parents, children


@dataclass(frozen=True)
class Sweep:
    folder: Path
    """The sweep's storage (``--out``)."""
    uri: str
    out: str
    """What the runner printed."""
    wall: float


@pytest.fixture(scope="module")
def e2e(cluster, tmp_path_factory) -> Sweep:
    """A 2-cell smoke grid with a paper row, run once for the module's tests."""
    tmp_path = tmp_path_factory.mktemp("e2e")
    argv, uri = _sweep(
        tmp_path,
        "name: e2e\ngrid: {priors.point_size: [0.02, 0.04]}\n"
        "paper: {table: T5, rows: [{label: size 0.04, when: {priors.point_size: 0.04}, values: {eval/f1: 0.461}}]}\n",
    )
    printed = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(printed):
        assert run.main(argv) == 0
    return Sweep(tmp_path / "results", uri, printed.getvalue(), time.perf_counter() - t0)


def test_grid_of_two_cells_end_to_end(e2e):
    out, uri = e2e.out, e2e.uri
    assert "profile in force: smoke" in out
    assert f"mlflow ui --backend-store-uri {uri} --host 127.0.0.1" in out
    table = out[out.index("e2e — profile smoke"):]
    assert (
        "point_size=0.02" in table and "point_size=0.04" in table and "0.461" in table and "baseline: sphere" in table
    )
    folder = e2e.folder / "e2e" / "smoke"
    assert (folder / "results.md").read_text().count("| point_size=0.0") == 2
    here = machine_record()
    assert f"- machine: {here['cpu_model']} ({here['cpu_isa']}), ATen {here['cpu_capability']}, " in (
        folder / "results.md").read_text()
    assert (folder / "results.csv").read_text().splitlines()[0].startswith("cell,")

    client, parents, children = _children(uri, "e2e")
    children = [c for c in children if "rerun_of" not in c.data.tags]  # the re-run test's run joins the experiment
    assert len(parents) == 1 and len(children) == 2
    parent = parents[0]
    assert {a.path for a in client.list_artifacts(parent.info.run_id)} >= {
        "spec.yaml",
        "plan.json",
        "results.md",
        "results.csv",
    }
    assert sorted(r.info.run_name for r in children) == ["point_size=0.02 · seed 0", "point_size=0.04 · seed 0"]
    for child in children:
        assert child.info.status == "FINISHED"
        assert child.data.tags["mlflow.parentRunId"] == parent.info.run_id
        assert child.data.tags["profile"] == "smoke" and child.data.tags["seed"] == "0"
        assert child.data.params["priors.point_size"] in ("0.02", "0.04") and child.data.params["train.steps"] == "20"
        loss = client.get_metric_history(child.info.run_id, "train/loss")
        assert [m.step for m in sorted(loss, key=lambda m: m.step)] == [5, 10, 15, 20]
        assert [m.step for m in client.get_metric_history(child.info.run_id, "eval/f1")] in ([10, 20], [20, 10])
        # Per category: the last evaluation's score once, as a final/… metric at the last step.
        assert [m.step for m in client.get_metric_history(child.info.run_id, "final/f1/chair")] == [20]
        assert child.data.metrics["final/f1/chair"] >= 0 and "final/f1/chair" not in child.data.params
        assert not client.get_metric_history(child.info.run_id, "eval/f1/chair")
        files = last_eval_files(client, child.info.run_id)  # eval/step_0000020/{panels,clouds}/
        assert any(f.endswith(".ply") for f in files) and any(f.endswith(".png") for f in files)
        assert "config.yaml" in {a.path for a in client.list_artifacts(child.info.run_id)}
    print(f"\n2-cell smoke grid: {e2e.wall:.1f} s wall")


def test_optuna_search_with_asha_stops_a_trial(cluster, tmp_path):
    # train/loss grows with λ (it includes λ × the prior term), so ASHA has a clear loser to stop.
    argv, uri = _sweep(tmp_path, """
name: opt
search:
  kind: optuna
  num_samples: 5
  seed: 3
  space: {priors.lambda_3d: {type: log_float, low: 1.0e-3, high: 30.0}}
metric: {name: train/loss, mode: min}
scheduler: {kind: asha, grace_evals: 1, reduction_factor: 2}
""")
    assert run.main(argv) == 0
    client, _, children = _children(uri, "opt")
    assert len(children) == 5
    lambdas = {c.data.params["priors.lambda_3d"] for c in children}
    assert len(lambdas) == 5 and all(1e-3 <= float(v) <= 30.0 for v in lambdas)
    assert len({c.data.tags["trial_id"] for c in children}) == 5
    stopped = [c for c in children if c.data.tags.get("stopped_early") == "true"]
    assert stopped, [(c.info.run_name, c.data.tags) for c in children]
    for c in stopped:
        assert max(m.step for m in client.get_metric_history(c.info.run_id, "train/loss")) < 20


BOILERPLATE = ("Checkpoint successfully created at", "Running in local mode", "Configuration for experiment",
               "TensorBoard", "View detailed results here", "Creating initial MLflow database tables", "alembic")


def test_a_diverging_trial_fails_with_its_reason_and_the_sweep_goes_on(cluster, tmp_path, capfd):
    argv, uri = _sweep(tmp_path, "name: nan\ngrid: {train.lr: [1.0e-3, 1.0e+30]}\n")
    assert run.main(argv) == 0
    captured = capfd.readouterr()
    out = captured.out
    assert "✗ failed [lr=1e+30 · seed 0]: cdm.optim.TrainingDiverged: " in out and "NaN or infinite" in out
    assert "0/1 (1 failed)" in out
    # Output to a pipe: Ray's and MLflow's boilerplate silenced, no colour codes, the error still shown,
    # and the progress line's last word (one line, not redrawn in place).
    everything = captured.out + captured.err
    assert [line for line in everything.splitlines() if any(b in line for b in BOILERPLATE)] == []
    assert "\x1b[" not in everything and "\r" not in everything
    assert "TrainingDiverged" in captured.err or out.count("TrainingDiverged") >= 1
    assert "sweep: 1/2 done, 0 running, 1 failed · " in out and "/40 steps · " in out
    assert "watch it live: mlflow ui --backend-store-uri " in out and "#/experiments/" in out
    _, _, children = _children(uri, "nan")
    status = {c.info.run_name: (c.info.status, c.data.tags.get("error", "")) for c in children}
    assert status["lr=0.001 · seed 0"][0] == "FINISHED"
    assert status["lr=1e+30 · seed 0"][0] == "FAILED" and "TrainingDiverged" in status["lr=1e+30 · seed 0"][1]
    csv = (tmp_path / "results" / "nan" / "smoke" / "results.csv").read_text()
    assert "lr=1e+30" in csv and ",1," in csv.splitlines()[2]


def test_rerun_reproduces_a_trial_exactly_and_reports_another_commit(e2e, capsys):
    uri = e2e.uri
    client, _, children = _children(uri, "e2e")
    child = next(c for c in children if c.info.run_name == "point_size=0.04 · seed 0")
    tags = child.data.tags
    assert tags["repro.git_commit"] and tags["repro.config_hash"] and tags["repro.version_torch"]
    assert {k: tags[f"repro.{k}"] for k in MACHINE_KEYS} == machine_record()
    assert client.list_artifacts(child.info.run_id, "environment")[0].path == PACKAGES_FILE
    assert tags["repro.data_fingerprint"].startswith("train ") and tags["eval_set"]
    capsys.readouterr()
    rerun_argv = [child.info.run_id, "--tracking-uri", uri, "--out", str(e2e.folder / "reruns")]
    assert rerun.main(rerun_argv) == 0
    out = capsys.readouterr().out
    assert "reproduced exactly" in out and "DIFFERENT" not in out
    again = [
        r for r in client.search_runs([child.info.experiment_id]) if r.data.tags.get("rerun_of") == child.info.run_id
    ]
    assert len(again) == 1
    assert again[0].data.metrics["eval/cd"] == child.data.metrics["eval/cd"]
    assert again[0].data.metrics["eval/f1"] == child.data.metrics["eval/f1"]

    # Another CPU type: named before training, and in the rows after it; the scores still match here.
    epyc = "AMD EPYC 7B13 64-Core Processor"
    client.set_tag(child.info.run_id, "repro.cpu_model", epyc)
    assert rerun.main(rerun_argv) == 1
    out = capsys.readouterr().out
    warning = "warning: this machine differs from the recorded run's; on CPU each of these can change the numbers"
    assert out.index(warning) < out.index("step 5/") and f"\n  repro.cpu_model: recorded {epyc}, here " in out
    assert re.search(r"\nrepro\.cpu_model +AMD EPYC 7B13 .*DIFFERENT\n", out)
    assert re.search(r"\neval/f1 +(\S+) +\1 +same\n", out)
    client.set_tag(child.info.run_id, "repro.cpu_model", tags["repro.cpu_model"])

    client.set_tag(child.info.run_id, "repro.git_commit", "0" * 40)
    assert rerun.main(rerun_argv) == 2
    err = capsys.readouterr().err
    assert f"recorded commit {'0' * 40}" in err and "--force" in err
    client.set_tag(child.info.run_id, "repro.git_commit", tags["repro.git_commit"])
    client.set_tag(child.info.run_id, "repro.config_hash", "0" * 16)
    assert rerun.main(rerun_argv) == 2
    assert f"differs from the recorded {'0' * 16}" in capsys.readouterr().err
    client.set_tag(child.info.run_id, "repro.config_hash", tags["repro.config_hash"])


def test_progress_line_counts_steps_across_trials_in_place_on_a_terminal(cluster):
    import io
    from types import SimpleNamespace

    from sweeps.execute.progress import StepReporter, SweepProgress

    for tty in (True, False):
        out = io.StringIO()
        progress = SweepProgress(f"p{tty}", trials=3, steps=100, label=lambda t: t.label, predicted_s=600.0, tty=tty,
                                 stream=out, refresh_s=0.05, every_s=0.05)
        a, b = (
            SimpleNamespace(label="a", last_result={"step": 100}),
            SimpleNamespace(label="b", last_result={"step": 40}),
        )
        progress.on_trial_start(0, [], a)
        progress.on_trial_start(0, [], b)
        reporter = StepReporter(f"p{tty}", "b")  # as a trial reports, through the sweep's named actor
        reporter.on_step(40, {})
        ray.get(reporter.counter.snapshot.remote())  # the fire-and-forget record has landed
        progress.on_trial_complete(0, [], a)
        time.sleep(0.3)
        progress.close()
        text = out.getvalue()
        # 140 of 300 steps done: 600 s × (1 − 140/300) = 5.3 min left by the calibration.
        last = r"sweep: 1/3 done, 1 running, 0 failed · 140/300 steps · \d+:\d\d elapsed, ~5\.3 min left \(calibrated\)"
        if tty:  # redrawn over itself: clear the line, draw, back to its start; a newline only at the end
            assert re.fullmatch(r"(\x1b\[2K[^\n]*\r)*\x1b\[2K" + last + r"\r\n", text) and text.count("\n") == 1
        else:
            assert re.fullmatch(last, text.splitlines()[-1]) and "\x1b" not in text and "\r" not in text


def test_a_crash_after_the_parent_run_exists_marks_it_failed(cluster, tmp_path, monkeypatch):
    """An unexpected error once the parent run is open (here: the trials' runner itself raising) reaches
    the user as it is, and leaves the parent run FAILED, not RUNNING forever in the UI."""
    import sweeps.execute.driver

    def broken(*args, **kwargs):
        raise RuntimeError("the trials' runner broke")

    monkeypatch.setattr(sweeps.execute.driver, "run_sweep", broken)
    argv, uri = _sweep(tmp_path, "name: crash\ngrid: {priors.point_size: [0.02]}\n")
    with pytest.raises(RuntimeError, match="runner broke"):
        run.main(argv)
    _, parents, children = _children(uri, "crash")
    assert [p.info.status for p in parents] == ["FAILED"] and children == []


def test_a_sweep_at_another_f1_threshold_labels_f1_so_in_its_table_store_and_report(cluster, tmp_path):
    """``--set eval.f1_threshold=0.02``: the printed table, results.md, each child's tag, param and description,
    the parent's description and the report's table say F1@0.02; F1@0.01 appears nowhere; the keys stay eval/f1."""
    from sweeps.results.sweep import open_sweep, results_table, trial_records

    argv, uri = _sweep(tmp_path, "name: tau\ngrid: {priors.point_size: [0.02]}\n", "--set", "eval.f1_threshold=0.02")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert run.main(argv) == 0
    client, parents, children = _children(uri, "tau")
    record = open_sweep(uri, "tau")
    texts = {
        "printed": printed.getvalue(),
        "results.md": next((tmp_path / "results").rglob("results.md")).read_text(),
        "parent description": parents[0].data.tags["mlflow.note.content"],
        "child description": children[0].data.tags["mlflow.note.content"],
        "report": results_table(record, trial_records(record)).text(),
    }
    for name, text in texts.items():
        flat = " ".join(text.split())
        assert "F1@0.01" not in flat, name
        assert "F1@0.02" in flat or name == "parent description", name
    assert "F1 is F1@0.02 on the squared distance" in " ".join(texts["printed"].split())
    assert children[0].data.tags["f1"] == "F1@0.02 sq. dist = 0.141421 world"
    assert children[0].data.params["eval.f1_threshold"] == "0.02"
    assert "eval/f1" in client.get_run(children[0].info.run_id).data.metrics


def test_a_synced_trial_folder_never_holds_a_temporary_file_and_nothing_prints_a_traceback(cluster, tmp_path, capfd,
                                                                                            caplog):
    """Tune's driver copies each trial's staging folder to storage every second, listing then reading every file;
    a temporary file renamed in between made it log a traceback. Here a trial writes its evaluation files at every
    step while a watcher lists that folder without pause: it never sees a temporary file, and nothing prints a
    traceback."""
    artifacts = Path(ray._private.worker.global_worker.node.get_session_dir_path()) / "artifacts"
    seen: set[str] = set()
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            for folder, folders, files in os.walk(artifacts):
                if "/driver_artifacts" in folder:  # what the driver copies; trials write in node-local scratch
                    seen.update(folders, files)
            time.sleep(0.002)  # a file lives ~ms while written; leave the trial its CPU

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    argv, _ = _sweep(tmp_path, "name: sync\ngrid: {priors.point_size: [0.02]}\n"
                               "profiles: {smoke: {budget: {steps: 20, eval_every: 1}}}\n")
    try:
        assert run.main(argv) == 0
    finally:
        done.set()
        watcher.join()
    captured = capfd.readouterr()
    # Ray's syncer logs its failure as a WARNING with the traceback (to stderr; under pytest, to the log capture).
    assert "Traceback" not in captured.out + captured.err + caplog.text
    assert "result.json" in seen and any(n.startswith("trial_") for n in seen)  # the watcher saw the trial's folder
    assert sorted(n for n in seen if TEMP_NAME.fullmatch(n) or n.startswith(".tmp_step_")) == []
