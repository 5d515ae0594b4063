"""cdm/io/safetensors.py: files the ``safetensors`` package reads and writes alike, a header checked before any
tensor is made, and trees of tensors and plain data kept exactly (types, key types, non-finite floats)."""

from __future__ import annotations

import json
import math

import pytest
import safetensors.torch
import torch

from cdm.io.safetensors import MAX_HEADER_BYTES, decode_tree, encode_tree, read_safetensors, write_safetensors

TENSORS = {"w": torch.arange(6.0).reshape(2, 3), "step": torch.tensor(7, dtype=torch.int64),
           "half": torch.tensor([1.5, -2.0], dtype=torch.bfloat16), "mask": torch.tensor([True, False, True]),
           "empty": torch.zeros(0, 4), "bytes": torch.arange(5, dtype=torch.uint8), "d": torch.tensor([math.pi])}


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("mapped", [False, True])
def test_written_here_read_by_the_package_and_written_by_it_read_here(tmp_path, mapped):
    ours, theirs = tmp_path / "ours.safetensors", tmp_path / "theirs.safetensors"
    write_safetensors(ours, TENSORS, {"format": "pt"}, "out")
    assert _same(safetensors.torch.load_file(ours), TENSORS)
    tensors, metadata = read_safetensors(ours, "x", mapped=mapped)
    assert _same(tensors, TENSORS) and metadata == {"format": "pt"} and list(tensors) == list(TENSORS)
    safetensors.torch.save_file(TENSORS, theirs, metadata={"k": "v"})
    tensors, metadata = read_safetensors(theirs, "x", mapped=mapped)
    assert _same(tensors, TENSORS) and metadata == {"k": "v"}


def test_a_header_past_the_cap_or_metadata_that_is_not_strings_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "w.safetensors"
    path.write_bytes((MAX_HEADER_BYTES + 1).to_bytes(8, "little") + b"{}")
    with pytest.raises(ValueError, match=rf"^x: {path} is not a safetensors file .*header says {MAX_HEADER_BYTES + 1} "
                                         rf"bytes, the file holds 10; at most {MAX_HEADER_BYTES} are read$"):
        read_safetensors(path, "x")
    header = json.dumps({"__metadata__": {"n": 1}}).encode()
    path.write_bytes(len(header).to_bytes(8, "little") + header)
    with pytest.raises(ValueError, match=rf"^x: {path}: its __metadata__ is not a map of strings$"):
        read_safetensors(path, "x")
    with pytest.raises(ValueError, match=r"^out: a tensor's name is 3 \(int\)"):
        write_safetensors(path, {3: torch.zeros(1)}, {}, "out")
    assert path.read_bytes().endswith(header)  # the refused write left the file as it was


def test_a_tree_of_tensors_and_plain_data_round_trips_with_its_types(tmp_path):
    tree = {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.ones(2)}, 10**6: {}},
            "param_groups": [{"betas": (0.9, 0.99), "lr": float("nan"), "eps": float("-inf"), "params": [0, 1],
                              "fused": True, "name": None}], "__odd": "a key that looks like a marker"}
    data, tensors = encode_tree(tree, "optimizer")
    assert sorted(tensors) == ["optimizer.state.0.exp_avg", "optimizer.state.0.step"]
    write_safetensors(tmp_path / "t.safetensors", tensors, {"tree": json.dumps(data)}, "out")
    read, metadata = read_safetensors(tmp_path / "t.safetensors", "x")
    back = decode_tree(json.loads(metadata["tree"]), read, "x")
    group = back["param_groups"][0]
    assert set(back["state"]) == {0, 10**6} and torch.equal(back["state"][0]["exp_avg"], torch.ones(2))
    assert group["betas"] == (0.9, 0.99) and math.isnan(group["lr"]) and group["eps"] == -math.inf
    assert back["__odd"] == tree["__odd"] and group["fused"] is True and group["name"] is None
    with pytest.raises(ValueError, match=r"^x: \{\"__tensor__\": \"missing\"\} names no tensor of the file"):
        decode_tree({"__tensor__": "missing"}, {}, "x")
    with pytest.raises(ValueError, match=r"^optimizer\.f: a builtin_function_or_method is neither a tensor nor "
                                         "plain data$"):
        encode_tree({"f": len}, "optimizer")
