"""python -m cdm: bad input exits 2 with one clear line and writes nothing; the happy path works."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cdm.config import load_config
from cdm.data import build_dataset
from tests.conftest import TINY


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cdm", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def render_input(config: Path) -> np.ndarray:
    """A held-out procedural view as a BGR uint8 image, the way a user's photo arrives."""
    sample = build_dataset(load_config(config), "val")[0]
    rgb = (sample.image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    return rgb[..., ::-1].copy()


def write_config(tmp_path: Path, **groups) -> Path:
    tree = {k: dict(v) for k, v in TINY.items()}
    for group, values in groups.items():
        tree.setdefault(group, {}).update(values)
    tree["train"]["out_dir"] = str(tmp_path / "out")
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(tree))
    return path


@pytest.mark.parametrize(
    "groups,extra,needle",
    [
        ({"priors": {"lambda_3d": -1}}, [], "priors.lambda_3d"),
        ({}, ["--set", "priors.lamda=1"], "priors.lamda"),
        ({"priors": {"num_views": 0}}, [], "priors.num_views"),
        ({"data": {"kind": "meshes", "root": "/nonexistent/meshes"}}, [], "data.root"),
    ],
)
def test_bad_input_exits_2_and_writes_nothing(tmp_path, groups, extra, needle):
    config = write_config(tmp_path, **groups)
    out = run_cli("train", "--config", str(config), *extra, cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert needle in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "out").exists()


def test_empty_and_corrupt_mesh_folders(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = run_cli(
        "train",
        "--config",
        str(write_config(tmp_path, data={"kind": "meshes", "root": str(empty), "categories": []})),
        cwd=tmp_path,
    )
    assert out.returncode == 2 and "data.root" in out.stderr
    corrupt = tmp_path / "corrupt" / "chair"
    corrupt.mkdir(parents=True)
    for i in range(4):
        (corrupt / f"m{i}.obj").write_text("this is not a mesh\n")
    out = run_cli(
        "train",
        "--config",
        str(write_config(tmp_path, data={"kind": "meshes", "root": str(corrupt.parent), "categories": []})),
        cwd=tmp_path,
    )
    assert out.returncode == 2 and "m0.obj" in out.stderr, out.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_train_evaluate_reconstruct(tmp_path):
    config = write_config(tmp_path, train={"steps": 4, "eval_every": 4})
    out = run_cli("train", "--config", str(config), "--out", "trained", cwd=tmp_path)  # --out over train.out_dir
    assert out.returncode == 0, out.stderr
    assert not (tmp_path / "out").exists()
    ckpt = next((tmp_path / "trained" / "checkpoints").glob("step_*"))
    out = run_cli("evaluate", "--checkpoint", str(ckpt), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "eval/cd" in out.stdout and "baseline/sphere/cd" in out.stdout
    image = tmp_path / "input.png"
    cv2.imwrite(str(image), render_input(config))
    ply = tmp_path / "cloud.ply"
    out = run_cli("reconstruct", "--checkpoint", str(ckpt), "--image", str(image), "--ply", str(ply), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    lines = ply.read_text().splitlines()
    assert lines[2] == f"element vertex {TINY['data']['num_points']}"
    assert len(lines) == 7 + TINY["data"]["num_points"]
    out = run_cli("evaluate", "--checkpoint", str(tmp_path / "nope"), cwd=tmp_path)
    assert out.returncode == 2 and "checkpoint" in out.stderr


@pytest.mark.parametrize(
    "argv,said",
    [
        (["train", "--out", "a", "--set", "train.out_dir=b"], "--out a and --set train.out_dir=b name two folders"),
        (["prepare", "--root", "raw", "--out", "prep"], "data.kind: give --set data.kind=KIND; choose one of"),
        (["prepare", "--set", "data.kind=procedural", "--root", "raw", "--out", "prep"],
         "data.kind: 'procedural' cannot be prepared; choose one of"),
    ],
)
def test_out_and_data_kind_are_refused_in_one_line_before_anything_is_written(argv, said, tmp_path, monkeypatch,
                                                                               capsys):
    from cdm.__main__ import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {said}"), err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("command", [["evaluate"], ["reconstruct", "--image", "in.png", "--ply", "cloud.ply"]])
def test_a_uri_checkpoint_is_refused_in_one_line_naming_cdm_lab(command, capsys):
    from cdm.__main__ import main

    assert main([*command, "--checkpoint", "runs:/0a1b2c/model"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "runs:/0a1b2c/model is a URI" in err
    assert f"cdm-lab {command[0]} --checkpoint runs:/0a1b2c/model" in err
