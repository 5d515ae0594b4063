"""cdm/io/arrays.py: ``.npy`` and ``.npz`` headers read and capped before anything is allocated."""

from __future__ import annotations

import resource

import numpy as np
import pytest

from cdm.io.arrays import load_npy, load_npz
from tests.hostile_files import npy_header, write_npz


def test_an_npy_header_over_the_cap_is_refused_before_allocating(tmp_path):
    """(100000, 100000) float32 with no data: 37.3 GiB promised by a 128-byte file."""
    path = tmp_path / "0.npy"
    path.write_bytes(npy_header((100_000, 100_000)))
    with pytest.raises(
        ValueError,
        match=r"declares a float32 array of shape \(100000, 100000\) \(37.3 GiB\); "
        r"an array read here may hold at most 512 MiB",
    ):
        load_npy(path, "priors.depth_maps")
    path.write_bytes(npy_header((1000, 1000)) + b"\0" * 100)
    with pytest.raises(ValueError, match="is shorter than its header says"):
        load_npy(path, "priors.depth_maps")
    np.save(path, np.arange(6, dtype=np.float32).reshape(2, 3))
    assert load_npy(path, "priors.depth_maps").tolist() == [[0, 1, 2], [3, 4, 5]]
    np.save(path, np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="holds Python objects, refused"):
        load_npy(path, "priors.depth_maps")


def test_an_npz_bomb_is_refused_from_its_header_and_a_sum_of_members_from_theirs(tmp_path):
    path = tmp_path / "embeddings.npz"
    size = write_npz(path, {"a/b/c": np.ones(4, np.float32)}, bomb="procedural/chair/x")
    assert size < 2e6
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    with pytest.raises(
        ValueError, match=r"procedural/chair/x.npy declares a float32 array of shape \(423624704,\) \(1.6 GiB\)"
    ):
        load_npz(path, "model.global_embeddings")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - before < 100 * 2**20
    assert load_npz(path, "model.global_embeddings", names=True) == ["a/b/c", "procedural/chair/x"]
    write_npz(path, {f"o{i}": np.zeros(1000, np.float32) for i in range(5)})
    with pytest.raises(ValueError, match="declares more than 0 MiB of arrays"):
        load_npz(path, "f", total=12_000)
    assert sorted(load_npz(path, "f")) == [f"o{i}" for i in range(5)]
