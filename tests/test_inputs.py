"""Inputs of ``python -m cdm``: images (size, bit depth), checkpoints that unpickle objects, ``--out`` folders."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cdm.__main__ import MIN_IMAGE_SIDE, _load_image, _output_folder
from cdm.checkpoint import load_checkpoint


def _object(side: int, dtype=np.uint8) -> np.ndarray:
    """A grey square on black, BGR, at full scale of ``dtype`` times 0.6."""
    top = np.iinfo(dtype).max
    img = np.zeros((side, side, 3), dtype)
    img[side // 4: 3 * side // 4, side // 4: 3 * side // 4] = round(0.6 * top)
    return img


def test_16_bit_png_is_scaled_by_its_own_full_scale(tmp_path):
    cv2.imwrite(str(tmp_path / "8.png"), _object(64))
    cv2.imwrite(str(tmp_path / "16.png"), _object(64, np.uint16))
    assert cv2.imread(str(tmp_path / "16.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    rgb8, mask8 = _load_image(tmp_path / "8.png", 32)
    rgb16, mask16 = _load_image(tmp_path / "16.png", 32)
    assert rgb16.max().item() == pytest.approx(0.6, abs=1e-4)  # 39321 / 65535, not 39321 / 255
    assert torch.allclose(rgb8, rgb16, atol=1 / 255) and torch.equal(mask8, mask16)
    assert mask16.sum().item() == 16 * 16


def test_tiny_images_are_refused_or_warned(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "1.png"), _object(1))
    with pytest.raises(ValueError, match=rf"1×1 pixels; give at least {MIN_IMAGE_SIDE}×{MIN_IMAGE_SIDE}"):
        _load_image(tmp_path / "1.png", 224)
    cv2.imwrite(str(tmp_path / "20.png"), _object(20))
    rgb, _ = _load_image(tmp_path / "20.png", 224)
    assert rgb.shape == (3, 224, 224)
    assert "20×20 pixels, enlarged 11×" in capsys.readouterr().err
    cv2.imwrite(str(tmp_path / "64.png"), _object(64))
    _load_image(tmp_path / "64.png", 224)
    assert capsys.readouterr().err == ""


def test_out_folder_is_created_only_inside_the_working_directory(tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert _output_folder(Path("cloud.ply")) is None
    assert _output_folder(Path("new/sub/cloud.ply")) == work / "new" / "sub"
    with pytest.raises(ValueError, match="outside the working directory; create it first"):
        _output_folder(tmp_path / "elsewhere" / "cloud.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"] and not list(work.iterdir())


def test_a_checkpoint_holding_objects_is_refused_in_our_words(tmp_path):
    evil = tmp_path / "evil.pt"
    torch.save({"config": {}, "step": 0, "voxel_backend": "dense", "model": Path("/")}, evil)  # a PosixPath global
    with pytest.raises(ValueError, match=r"evil\.pt was written by cdm 0\.1\.0 \(torch\.save\); convert it"):
        load_checkpoint(evil)  # the project's own loader reads no pickle at all
    out = subprocess.run([sys.executable, "-m", "cdm", "convert", str(evil), "new"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)  # convert reads it inertly, and refuses it
    assert out.returncode == 2 and "holds Python objects other than tensors" in out.stderr, out.stderr
    assert "weights_only" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "new").exists()


def test_train_refuses_sizes_past_the_machines_memory_before_allocating(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "cdm", "train", "--set", "data.train_objects=100000000000"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "data.train_objects=100000000000" in out.stderr and "GiB" in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not list(tmp_path.iterdir())
