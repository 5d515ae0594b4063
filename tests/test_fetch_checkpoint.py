"""``cdm-lab evaluate/reconstruct --checkpoint URI``: MLflow fetches the files, the command reads a local copy.

:func:`cdm.lab.fetched_checkpoint` finds the fetcher (:func:`sweeps.lab.fetch`) through the installed entry point
``cdm_lab.checkpoint_fetchers`` (``pip install -e .`` records it)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from mlflow import MlflowClient

from cdm.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from cdm.config import load_config
from cdm.lab import fetched_checkpoint, main
from cdm.paths import names_a_uri


def test_uris_are_told_from_paths():
    assert all(map(names_a_uri, ("runs:/0a1b/model", "models:/cdm/1", "s3://bucket/x", "file:///tmp/x")))
    assert not any(map(names_a_uri, ("runs/cdm/checkpoints/step_0000020", "/abs/checkpoint.pt", "C:\\ckpt", "x")))


def test_a_local_checkpoint_is_passed_on_unchanged():
    argv = ["evaluate", "--checkpoint", "runs/cdm/checkpoints/step_0000020", "--set", "eval.num_objects=2"]
    with fetched_checkpoint(argv) as args:
        assert args is argv


def test_a_uri_is_fetched_into_a_folder_kept_while_the_command_runs(tmp_path):
    weights = {"layer.weight": torch.arange(6.0).reshape(3, 2)}
    saved = save_checkpoint(Checkpoint(load_config(None, {}).to_dict(), 7, "dense", weights), tmp_path / "model")
    for argv in (["--checkpoint", saved.parent.as_uri(), "--out", "x"], [f"--checkpoint={saved.parent.as_uri()}"]):
        with fetched_checkpoint(argv) as args:
            local = args[1] if args[0] == "--checkpoint" else args[0].removeprefix("--checkpoint=")
            assert args[2:] == argv[2:] and not names_a_uri(local)
            assert not Path(local).is_relative_to(tmp_path)  # a copy, not the original
            fetched = load_checkpoint(local)
            assert fetched.step == 7 and torch.equal(fetched.model["layer.weight"], weights["layer.weight"])
        assert not Path(local).exists()  # the copy goes with the command


def test_a_uri_mlflow_cannot_resolve_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    MlflowClient(uri).search_experiments()  # the store exists (a new one is created with lines of its own)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    capsys.readouterr()
    assert main(["evaluate", "--checkpoint", "runs:/0123456789abcdef/model"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --checkpoint: MLflow could not fetch runs:/0123456789abcdef/model (")
    assert err.count("\n") == 1 and "runs:/<run id>/model" in err
    missing = ["--checkpoint", "runs:/0123456789abcdef/model"]
    with pytest.raises(ValueError, match="0123456789abcdef"), fetched_checkpoint(missing):
        pass
