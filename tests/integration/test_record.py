"""A sweep's record outlives the machine's temporary folders (issue 53, "Where is my model?").

One smoke grid runs on a Ray cluster the runner starts itself, its temporary folder (``RAY_TMPDIR``) of this
module's own; then that folder is deleted, as ``ray stop`` and a reboot do. Every path the record names (MLflow
tags, results.md/csv, the printed lines) must still exist; each child's weights, logged as its MLflow model,
score through ``cdm-lab evaluate --checkpoint runs:/…`` what the trial scored; the best cell's model, registered
by ``--register``, loads with ``mlflow.pyfunc`` and scores through ``models:/…``; the report rebuilds and the
trial re-runs; and the sweep folder holds no file twice.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import mlflow
import numpy as np
import pytest
import ray
from mlflow import MlflowClient

from cdm.checkpoint import CHECKPOINT_FILE
from sweeps import report, rerun, run
from sweeps.execute.trial import sweep_scratch, trial_scratch
from sweeps.mlflow_model import model_checkpoint
from sweeps.results.sweep import open_sweep, results_table, trial_records

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
PATH = re.compile(r"(?<![\w.:/#])/(?:[\w.@+-]+/)*[\w.@+-]+")
"""An absolute path in a text (not the tail of a URL, ``http://host/x``, nor a UI link, ``#/experiments/1``)."""


REGISTERED = "cdm-record"
"""The registered model the sweep's best cell's model becomes (``--register``)."""


@dataclass(frozen=True)
class Swept:
    folder: Path
    """The sweep folder (``<storage>/<spec>/<profile>``)."""
    uri: str
    out: str
    ray_tmp: Path
    """Ray's temporary folder while the sweep ran; deleted before the tests read the record."""


@pytest.fixture(scope="module")
def swept(tmp_path_factory) -> Swept:
    tmp = tmp_path_factory.mktemp("record")
    # Short: Ray's socket paths under it must fit ~107 characters.
    ray_tmp = Path(tempfile.mkdtemp(prefix="cdmrec", dir="/tmp"))
    (tmp / "spec.yaml").write_text("name: record\ngrid: {priors.point_size: [0.02, 0.04]}\n")
    uri = f"sqlite:///{tmp}/mlflow.db"
    argv = [str(tmp / "spec.yaml"), "--smoke", "--out", str(tmp / "results"), "--tracking-uri", uri,
            "--register", REGISTERED]
    printed = io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(printed):
        patch.setenv("RAY_TMPDIR", str(ray_tmp))
        assert not ray.is_initialized()
        assert run.main(argv) == 0
    assert not ray.is_initialized()  # the runner stopped the cluster it started
    assert list(ray_tmp.glob("ray/session_2*")), "Ray kept its session elsewhere: the deletion below proves nothing"
    shutil.rmtree(ray_tmp)
    return Swept(tmp / "results" / "record" / "smoke", uri, printed.getvalue(), ray_tmp)


def _runs(uri: str):
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("record").experiment_id])
    parent = next(r for r in runs if r.data.tags.get("kind") == "sweep")
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id
                and "trial_id" in r.data.tags and "rerun_of" not in r.data.tags]
    return client, parent, children


def test_every_recorded_path_exists_after_rays_temporary_folder_is_gone(swept):
    client, parent, children = _runs(swept.uri)
    assert len(children) == 2
    recorded = {f"tag {k} of {r.info.run_name}": v for r in (parent, *children) for k, v in r.data.tags.items()
                if v.startswith("/")}
    assert parent.data.tags["sweep_dir"] == str(swept.folder)
    for child in children:
        tags = child.data.tags
        assert tags["tune_trial_dir"] == f"{swept.folder}/trial_{tags['trial_id']}"
        assert Path(tags["tune_trial_dir"], "result.json").is_file()
        # The newest Tune checkpoint, in the sweep's storage: the full state, to continue training from.
        assert Path(tags["checkpoint"]).parent == Path(tags["tune_trial_dir"])
        assert Path(tags["checkpoint"], CHECKPOINT_FILE).is_file()
        assert tags["model"] == f"runs:/{child.info.run_id}/model"
        # The scratch folder the trial trained in is gone: its checkpoints are in storage, its files in MLflow.
        assert not trial_scratch(str(swept.folder), tags["trial_id"]).exists()
    assert not sweep_scratch(str(swept.folder)).exists()  # and the sweep's own, once the sweep ended
    for name in ("results.md", "results.csv"):
        text = (swept.folder / name).read_text()
        recorded |= {f"{name}: {p}": p for p in PATH.findall(text)}
    recorded |= {f"printed: {p}": p for p in PATH.findall(swept.out)}
    assert {k for k in recorded if k.startswith("tag checkpoint")} and {k for k in recorded if "printed" in k}
    for where, path in recorded.items():
        assert not path.startswith(str(swept.ray_tmp)), f"{where} lies in Ray's temporary folder"
        assert Path(path).exists(), f"{where} is gone with Ray's temporary folder"


def test_each_trial_checkpoint_is_stored_once(swept):
    by_digest: dict[str, list[Path]] = {}
    for path in swept.folder.rglob("*"):
        if path.is_file() and path.stat().st_size >= 1024:
            by_digest.setdefault(hashlib.sha256(path.read_bytes()).hexdigest(), []).append(path)
    copies = [paths for paths in by_digest.values() if len(paths) > 1]
    assert not copies, f"byte-identical copies in the sweep folder: {copies}"
    checkpoints = sorted(swept.folder.rglob(CHECKPOINT_FILE))
    # Tune's two newest per trial (sweeps/execute/pruning.py), nothing else: no cdm/ copy beside them.
    assert [p.relative_to(swept.folder).parts[1] for p in checkpoints] == ["checkpoint_000000", "checkpoint_000001"] * 2


TUNE_STATE = re.compile(r"tuner\.pkl|params\.pkl|basic-variant-state-[0-9_-]+\.json|searcher-state-[0-9_-]+\.pkl"
                        r"|events\.out\.tfevents\..+")
"""Ray Tune's own state, which it pickles (docs/security.md, "What --resume trusts"), and its TensorBoard log:
no weights of ours."""


def _is_text(path: Path) -> bool:
    try:
        path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def test_the_sweep_folder_keeps_weights_in_safetensors_and_everything_else_in_text(swept):
    files = [p for p in swept.folder.rglob("*") if p.is_file()]
    assert not [p for p in files if p.suffix in (".pt", ".pth", ".bin", ".ckpt")]
    weights = sorted(p.relative_to(swept.folder) for p in files if p.suffix == ".safetensors")
    assert {p.name for p in weights} >= {"model.safetensors", "training.safetensors"}
    other = sorted(str(p.relative_to(swept.folder)) for p in files if p.suffix not in (".safetensors", ".png")
                   and not _is_text(p) and not TUNE_STATE.fullmatch(p.name))
    assert other == [], other


def test_safetensors_alone_loads_the_childs_weights(swept, tmp_path, monkeypatch):
    import safetensors.torch
    import torch

    from cdm.checkpoint import load_checkpoint

    _, _, children = _runs(swept.uri)
    child = min(children, key=lambda r: r.info.run_name)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", swept.uri)  # where MLflow looks a run's model up
    # The README's lines, as written there.
    folder = mlflow.artifacts.download_artifacts(child.data.tags["model"], dst_path=str(tmp_path))
    weights = safetensors.torch.load_file(f"{folder}/artifacts/checkpoint/model.safetensors")
    stored = load_checkpoint(Path(child.data.tags["checkpoint"])).model
    assert weights.keys() == stored.keys() and all(torch.equal(weights[k], v) for k, v in stored.items())


def _scores_as_logged(uri: str, checkpoint: str, child, cwd: Path) -> None:
    """``cdm-lab evaluate --checkpoint checkpoint`` (a new process) scores what ``child`` logged, leaving no
    temporary folder behind (its private TMPDIR holds no ``tmp*`` or ``cdm-checkpoint-*`` after it)."""
    private = cwd / "tmpdir"
    private.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": uri, "TMPDIR": str(private)}
    out = subprocess.run([sys.executable, "-m", "cdm.lab", "evaluate", "--checkpoint", checkpoint],
                         cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert _left_in(private) == []
    scores = dict(re.findall(r"^(eval/(?:f1|cd)) +([\d.]+)$", out.stdout, re.M))
    logged = child.data.metrics  # the trial's last evaluation, at the results table's precision
    assert abs(float(scores["eval/f1"]) - logged["eval/f1"]) <= 1e-3, (scores, logged)
    assert abs(float(scores["eval/cd"]) - logged["eval/cd"]) <= 1e-3 * logged["eval/cd"], (scores, logged)


def test_evaluate_scores_the_childs_weights_from_its_mlflow_run(swept, tmp_path, monkeypatch):
    _, _, children = _runs(swept.uri)
    child = min(children, key=lambda r: r.info.run_name)
    _scores_as_logged(swept.uri, child.data.tags["model"], child, tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", swept.uri)  # where MLflow looks a run's model up
    folder = model_checkpoint(Path(mlflow.artifacts.download_artifacts(child.data.tags["model"],
                                                                       dst_path=str(tmp_path))))
    full = Path(child.data.tags["checkpoint"])
    assert (folder / "model.safetensors").stat().st_size == (full / "model.safetensors").stat().st_size
    assert not (folder / "training.safetensors").exists()  # weights and EMA only: no optimiser state
    assert (full / "training.safetensors").is_file()  # the full checkpoint, in storage, keeps it


def test_the_best_cells_model_is_registered_and_loads_as_an_mlflow_model(swept, tmp_path, monkeypatch):
    client, parent, children = _runs(swept.uri)
    [version] = client.search_model_versions(f"name = '{REGISTERED}'")
    record = open_sweep(swept.uri, parent_run_id=parent.info.run_id)
    best = results_table(record, trial_records(record, objects=False)).best
    registered = next(c for c in children if c.info.run_id == version.run_id)
    assert best == registered.data.tags["cell"]  # the cell the results table stars
    assert f"registered as models:/{REGISTERED}/1" in swept.out
    monkeypatch.setenv("MLFLOW_TRACKING_URI", swept.uri)
    model = mlflow.pyfunc.load_model(registered.data.tags["model"])
    image = np.full((32, 32, 3), 255, np.uint8)
    image[8:24, 8:24] = (90, 90, 200)
    cloud = model.predict({"image": image})
    assert cloud.shape == (128, 3) and cloud.dtype == np.float32 and np.isfinite(cloud).all()  # smoke: 128 points
    _scores_as_logged(swept.uri, f"models:/{REGISTERED}/1", registered, tmp_path)


def _left_in(folder: Path) -> list[str]:
    """The temporary folders a command left in ``folder`` (its TMPDIR): Python's ``tmp*`` and ours."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(("tmp", "cdm-checkpoint-")))


def test_report_and_rerun_work_from_the_record_alone(swept, tmp_path, monkeypatch, capsys):
    _, _, children = _runs(swept.uri)
    monkeypatch.chdir(tmp_path)
    private = tmp_path / "tmpdir"  # the commands' temporary folder: what they leave there is counted below
    private.mkdir()
    monkeypatch.setenv("TMPDIR", str(private))
    monkeypatch.setattr(tempfile, "tempdir", None)  # read TMPDIR again
    assert report.main(["record", "--tracking-uri", swept.uri]) == 0
    rebuilt = tmp_path / "results" / "record" / "report" / "results.md"
    assert rebuilt.read_text() == (swept.folder / "results.md").read_text()
    capsys.readouterr()
    child = min(children, key=lambda r: r.info.run_name)
    assert rerun.main([child.info.run_id, "--tracking-uri", swept.uri]) == 0
    assert "reproduced exactly" in capsys.readouterr().out
    assert _left_in(private) == []
