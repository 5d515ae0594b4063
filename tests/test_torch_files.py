"""Torch files read as tensors and plain data only: what loads, and the three refusals in our words."""

from __future__ import annotations

import argparse

import pytest
import torch

from cdm.torch_files import load_tensors


def _load(file):
    return load_tensors(file, f"weights: {file}", "weights file", "Pass the weights alone.")


def test_tensors_and_plain_data_load_on_the_cpu(tmp_path):
    torch.save({"w": torch.arange(3.0), "step": 7, "names": ["a"]}, tmp_path / "ok.pt")
    loaded = _load(tmp_path / "ok.pt")
    assert torch.equal(loaded["w"], torch.arange(3.0)) and loaded["w"].device.type == "cpu"
    assert (loaded["step"], loaded["names"]) == (7, ["a"])


def test_pickled_objects_garbage_and_a_truncated_archive_are_refused_apart(tmp_path):
    torch.save({"cfg": argparse.Namespace(code=1)}, tmp_path / "objects.pt")
    with pytest.raises(ValueError, match=r"^weights: .*objects\.pt holds Python objects other than tensors .* "
                                         r"could run code from the file\. Pass the weights alone\.$") as refused:
        _load(tmp_path / "objects.pt")
    assert "weights_only" not in str(refused.value)  # torch's own advice would run the file's code
    (tmp_path / "garbage.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"^weights: .*garbage\.pt is not a readable weights file: not in torch's file format$"):
        _load(tmp_path / "garbage.pt")
    torch.save({"w": torch.zeros(1000)}, tmp_path / "cut.pt")
    (tmp_path / "cut.pt").write_bytes((tmp_path / "cut.pt").read_bytes()[:600])
    with pytest.raises(ValueError, match=r"^weights: .*cut\.pt is not a readable weights file \("):
        _load(tmp_path / "cut.pt")
