"""A trial's MLflow model: logged from code by the trial's own callback, loaded by ``mlflow.pyfunc`` in a fresh
Python, registered, and scored by ``cdm-lab evaluate --checkpoint models:/…``; on a SQLite store and on a real
``mlflow server`` with its artifact proxy."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import mlflow
import numpy as np
import pytest
from mlflow import MlflowClient
from mlflow.exceptions import MlflowException

from cdm.checkpoint import load_checkpoint
from cdm.lab import main
from cdm.train import fit
from sweeps.mlflow_model import model_checkpoint
from sweeps.results.register import RegisterError, best_trial, register_run
from sweeps.results.sweep import open_sweep
from sweeps.store.sweep_run import SweepRun
from sweeps.store.trial_run import TrialRun
from tests.conftest import tiny_config

ROOT = Path(__file__).resolve().parents[1]

slow = pytest.mark.slow  # trains a network, starts a server or a new Python


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A tiny network's checkpoint folder, after 2 training steps."""
    tmp = tmp_path_factory.mktemp("trained")
    return fit(tiny_config(tmp, **{"train.steps": 2, "train.eval_every": 2})).checkpoint_dir


def _object_image(height: int = 40, width: int = 48) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB: a reddish square on white."""
    image = np.full((height, width, 3), 255, np.uint8)
    image[height // 4: 3 * height // 4, width // 4: 3 * width // 4] = (200, 60, 40)
    return image


def _log_as_a_trial(uri: str, checkpoint: Path, steps: tuple[int, ...] = (2,)) -> str:
    """A child run of a new sweep, its model logged by the trial's callback at each of ``steps``; its run id."""
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, tiny_config(checkpoint))
    trial.on_start({"git_commit": "abc"})
    for step in steps:
        trial.on_checkpoint(step, checkpoint)
    return trial.run_id


_PREDICT = """
import json, sys
import numpy as np, mlflow
model = mlflow.pyfunc.load_model(sys.argv[1])
image = np.load(sys.argv[2])
a = model.predict({"image": image})
b = model.predict({"image": image}, params={"seed": 0})
c = model.predict(image, params={"seed": 1, "camera": [20.0, 90.0, 3.5, 2.0]})
np.save(sys.argv[3], a)
print(json.dumps({"shape": a.shape, "dtype": str(a.dtype), "finite": bool(np.isfinite(a).all()),
                  "same_seed": bool((a == b).all()), "other_seed_and_camera": float(np.abs(a - c).max())}))
"""


def _predict_in_a_fresh_python(uri: str, model_uri: str, tmp_path: Path) -> tuple[dict, np.ndarray]:
    """What a new Python (the package on its path, nothing else of this process) predicts for the test image."""
    np.save(tmp_path / "image.npy", _object_image())
    env = {"PATH": os.environ["PATH"], "HOME": os.environ.get("HOME", str(tmp_path)), "PYTHONPATH": str(ROOT),
           "MLFLOW_TRACKING_URI": uri}
    out = subprocess.run([sys.executable, "-c", _PREDICT, model_uri, str(tmp_path / "image.npy"),
                          str(tmp_path / "cloud.npy")], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1]), np.load(tmp_path / "cloud.npy")


def _check_prediction(report: dict, cloud: np.ndarray) -> None:
    assert report["shape"] == [128, 3] and report["dtype"] == "float32" and report["finite"]  # data.num_points
    assert report["same_seed"] and report["other_seed_and_camera"] > 1e-3
    assert cloud.shape == (128, 3) and 0 < np.abs(cloud).max() < 10


@slow
def test_a_trials_model_loads_in_a_fresh_python_and_samples_what_reconstruct_samples(trained, tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    run_id = _log_as_a_trial(uri, trained, steps=(1, 2))  # the second checkpoint's model replaces the first's
    client = MlflowClient(uri)
    assert client.get_run(run_id).data.tags["model"] == f"runs:/{run_id}/model"
    models = client.search_logged_models([client.get_run(run_id).info.experiment_id])
    assert [(m.name, m.source_run_id, m.status.to_proto()) for m in models] == [("model", run_id, 2)]  # READY
    report, cloud = _predict_in_a_fresh_python(uri, f"runs:/{run_id}/model", tmp_path)
    _check_prediction(report, cloud)
    info = mlflow.models.get_model_info(f"models:/{models[0].model_id}")
    assert info.metadata == {"step": 2, "git_commit": "abc"}
    assert info.signature.inputs.to_dict() == [
        {"name": "image", "type": "tensor", "tensor-spec": {"dtype": "uint8", "shape": (-1, -1, -1)}}]
    assert {p.name: p.default for p in info.signature.params.params} == {"camera": [20.0, 0.0, 3.5, 2.0], "seed": 0}
    # `cdm-lab reconstruct` on the same picture as a PNG (OpenCV writes BGR), seed 0, default camera.
    cv2.imwrite(str(tmp_path / "object.png"), cv2.cvtColor(_object_image(), cv2.COLOR_RGB2BGR))
    assert main(["reconstruct", "--checkpoint", f"runs:/{run_id}/model", "--image", str(tmp_path / "object.png"),
                 "--ply", str(tmp_path / "object.ply")]) == 0
    written = np.loadtxt(tmp_path / "object.ply", skiprows=7)  # ASCII PLY: 7 header lines, 6 decimals
    assert written.shape == (128, 3) and np.abs(written - cloud).max() < 1e-5


@slow
def test_bad_input_is_one_error_naming_the_input_or_param(trained, tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    run_id = _log_as_a_trial(uri, trained)
    model = mlflow.pyfunc.load_model(f"runs:/{run_id}/model")
    with pytest.raises(MlflowException, match="uint8"):
        model.predict({"image": _object_image().astype(np.float32)})
    with pytest.raises(ValueError, match=r"^camera: \[20.0, 0.0, 3.5\] is not \[elev°, azim°, dist, focal\]"):
        model.predict({"image": _object_image()}, params={"camera": [20.0, 0.0, 3.5]})
    with pytest.raises(ValueError, match="^image: the input is 8×8 pixels; give at least 16×16"):
        model.predict({"image": _object_image(8, 8)})
    rgba = np.concatenate([_object_image(), np.zeros((40, 48, 1), np.uint8)], axis=2)
    rgba[10:30, 12:36, 3] = 255  # alpha: the mask, as a PNG cut-out carries it
    assert model.predict({"image": rgba}).shape == (128, 3)


@slow
def test_a_registered_model_is_scored_by_evaluate_as_its_run_is(trained, tmp_path, monkeypatch, capsys):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    run_id = _log_as_a_trial(uri, trained)
    client = MlflowClient(uri)
    version = register_run(client, run_id, "cdm-chairs")
    assert (version.name, version.version, version.run_id) == ("cdm-chairs", 1, run_id)
    [model] = client.search_logged_models([client.get_run(run_id).info.experiment_id])
    assert json.loads(model.tags["mlflow.modelVersions"]) == [{"name": "cdm-chairs", "version": 1}]  # linked in the UI
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    scores = {}
    for checkpoint in (str(trained), "models:/cdm-chairs/1", f"runs:/{run_id}/model"):
        assert main(["evaluate", "--checkpoint", checkpoint]) == 0
        scores[checkpoint] = dict(re.findall(r"^(eval/(?:f1|cd)) +([\d.]+)$", capsys.readouterr().out, re.M))
    assert len({json.dumps(s, sort_keys=True) for s in scores.values()}) == 1 and scores[str(trained)]["eval/cd"]
    folder = Path(mlflow.artifacts.download_artifacts("models:/cdm-chairs/1", dst_path=str(tmp_path / "down"),
                                                      tracking_uri=uri))
    assert load_checkpoint(model_checkpoint(folder)).step == load_checkpoint(trained).step


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory):
    """A real ``mlflow server`` on 127.0.0.1 proxying artifacts into its own folder: (its URI, that folder)."""
    tmp = tmp_path_factory.mktemp("server")
    port = _free_port()
    artifacts = tmp / "artifacts"
    log = (tmp / "server.log").open("w")
    server = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
         "--backend-store-uri", f"sqlite:///{tmp}/server.db", "--serve-artifacts", "--artifacts-destination",
         str(artifacts)], stdout=log, stderr=subprocess.STDOUT, cwd=tmp)
    uri = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            with urllib.request.urlopen(f"{uri}/health", timeout=2) as answer:
                if answer.status == 200:
                    break
        except OSError:
            if server.poll() is not None or time.monotonic() > deadline:
                server.kill()
                pytest.fail(f"mlflow server did not start: {(tmp / 'server.log').read_text()[-2000:]}")
            time.sleep(0.5)
    yield uri, artifacts
    server.terminate()
    server.wait(timeout=30)
    log.close()


@slow
def test_on_an_mlflow_server_the_model_travels_through_its_artifact_proxy(trained, mlflow_server, tmp_path,
                                                                          monkeypatch, capsys):
    uri, artifacts = mlflow_server
    run_id = _log_as_a_trial(uri, trained)
    client = MlflowClient(uri)
    model = client.search_logged_models([client.get_run(run_id).info.experiment_id])[0]
    assert model.artifact_location.startswith("mlflow-artifacts:/")  # the client never writes the store itself
    stored = {p.name for p in artifacts.rglob("*") if p.is_file()}
    assert {"MLmodel", "mlflow_model.py"} <= stored and not (tmp_path / "mlruns").exists()
    _check_prediction(*_predict_in_a_fresh_python(uri, f"runs:/{run_id}/model", tmp_path))
    register_run(client, run_id, "cdm-served")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    assert main(["evaluate", "--checkpoint", "models:/cdm-served/1"]) == 0
    assert re.search(r"^eval/cd +[\d.]+$", capsys.readouterr().out, re.M)


def test_a_bad_registered_name_is_one_line_and_exit_2_before_anything_starts(tmp_path, capsys):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    assert main(["register", "exp", "--name", "cdm/chairs", "--tracking-uri", uri]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --name: 'cdm/chairs' is not a model name") and err.count("\n") == 1
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: named\ngrid: {priors.point_size: [0.02, 0.04]}\n")
    out = tmp_path / "results"
    assert main(["run", str(spec), "--smoke", "--out", str(out), "--tracking-uri", uri, "--register", "a b"]) == 2
    assert "error: --register: 'a b' is not a model name" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "mlflow.db").exists()  # refused before the sweep's folder or store


def _sweep_of(tmp_path: Path, f1s: dict[str, float]) -> str:
    """A finished sweep in a new store: one child per ``"<cell> · seed <n>"`` with its ``eval/f1``; its URI."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    client = MlflowClient(uri)
    experiment = client.create_experiment("t", artifact_location=(tmp_path / "mlruns").as_uri())
    parent = client.create_run(experiment, tags={"kind": "sweep", "profile": "smoke"}).info.run_id
    (tmp_path / "t.yaml").write_text("name: t\ngrid: {priors.point_size: [0.02, 0.04]}\n")
    (tmp_path / "plan.json").write_text('{"cells": []}')
    for name in ("t.yaml", "plan.json"):
        client.log_artifact(parent, str(tmp_path / name))
    for label, f1 in f1s.items():
        child = client.create_run(experiment, run_name=label, tags={"mlflow.parentRunId": parent,
                                                                     "cell": label.split(" · ")[0]}).info.run_id
        client.log_metric(child, "eval/f1", f1)
        client.set_terminated(child, "FINISHED")
    return uri


def test_the_best_trial_is_the_starred_cells_best_seed_and_a_tie_registers_nothing(tmp_path, capsys):
    uri = _sweep_of(tmp_path / "apart", {"a · seed 0": 0.50, "b · seed 0": 0.58, "b · seed 1": 0.62})
    assert best_trial(open_sweep(uri, "t")).outcome.label == "b · seed 1"  # eval/f1, max: the spec's metric
    uri = _sweep_of(tmp_path / "tied", {"a · seed 0": 0.6001, "b · seed 0": 0.6002})
    with pytest.raises(RegisterError, match=r"no best cell by eval/f1 \(max\).*leaders tie at the printed precision"):
        best_trial(open_sweep(uri, "t"))
    capsys.readouterr()
    assert main(["register", "t", "--name", "cdm-t", "--tracking-uri", uri]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: sweep ") and err.count("\n") == 1 and not MlflowClient(uri).search_registered_models()


@pytest.mark.parametrize("artifacts, said", [
    ("{checkpoint: {path: ../../outside}}", "places its checkpoint outside the model"),
    ("{weights: {path: artifacts/weights}}", "is an MLflow model without a 'checkpoint' artifact"),
])
def test_an_mlmodel_that_points_elsewhere_is_refused_in_one_line(tmp_path, capsys, artifacts, said):
    model = tmp_path / "model"
    model.mkdir()
    (model / "MLmodel").write_text(f"flavors:\n  python_function:\n    artifacts: {artifacts}\n")
    with pytest.raises(ValueError, match=said):
        model_checkpoint(model)
    assert model_checkpoint(tmp_path) == tmp_path  # no MLmodel: a checkpoint folder, as 0.1.0 logged it
    assert main(["evaluate", "--checkpoint", model.as_uri()]) == 2
    err = capsys.readouterr().err  # after MLflow's download progress bar
    assert err.count("error:") == 1 and err.splitlines()[-1].startswith("error: --checkpoint: ") and said in err
