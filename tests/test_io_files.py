"""cdm/io/files.py: regular files only, caps checked before anything is allocated, names that stay inside."""

from __future__ import annotations

import json
import os
import resource

import numpy as np
import pytest

from cdm.io.files import (
    MAX_JSON_DEPTH,
    annotation_cap,
    inside,
    load_npy,
    load_npz,
    object_id_parts,
    open_regular,
    parse_json,
    plain_name,
    read_bounded,
    read_gzip,
    read_json,
)
from tests.hostile_files import gzip_bomb, nested_json, npy_header, write_npz


@pytest.mark.parametrize(
    "kind,said", [("fifo", "is a FIFO"), ("folder", "is a folder"), ("dev_zero", "is a character device")]
)
def test_open_regular_refuses_what_is_not_a_regular_file_before_reading(tmp_path, kind, said):
    path = tmp_path / "checkpoint.pt"
    if kind == "fifo":
        os.mkfifo(path)  # no writer: a blocking open would never return
    elif kind == "folder":
        path.mkdir()
    else:
        path.symlink_to("/dev/zero")
    with pytest.raises(ValueError, match=f"^field: {path} {said}; expected a regular file$"):
        open_regular(path, "field")


def test_open_regular_follows_a_link_to_a_regular_file_and_reads_it(tmp_path):
    (tmp_path / "real.json").write_text('{"a": [1, 2]}')
    (tmp_path / "link.json").symlink_to(tmp_path / "real.json")
    assert read_json(tmp_path / "link.json", "field") == {"a": [1, 2]}


def test_read_bounded_refuses_a_file_over_its_cap_by_size(tmp_path):
    (tmp_path / "big.txt").write_bytes(b"x" * 1001)
    assert read_bounded(tmp_path / "big.txt", "f", cap=1001) == b"x" * 1001
    with pytest.raises(ValueError, match="is 1001 bytes; at most 1000 are read"):
        read_bounded(tmp_path / "big.txt", "f", cap=1000)


def test_a_gzip_bomb_stops_at_the_cap_with_memory_near_it(tmp_path):
    """3 GB of zeros in 3 MB: refused once 64 MiB are out, the process grown by about that, not 3 GB."""
    bomb = tmp_path / "frame_annotations.jgz"
    assert gzip_bomb(bomb, 3.0) < 4e6
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    with pytest.raises(
        ValueError, match=f"data.root: {bomb} decompresses to more than 64 MiB; set CDM_MAX_ANNOTATION_MIB"
    ):
        read_gzip(bomb, "data.root", cap=64 * 2**20)
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - before
    assert grown < 200 * 2**20


def test_the_annotation_cap_is_read_from_the_environment(monkeypatch):
    assert annotation_cap() == 256 * 2**20
    monkeypatch.setenv("CDM_MAX_ANNOTATION_MIB", "1024")
    assert annotation_cap() == 2**30
    for junk in ("0", "-5", "²", "1" * 5001, ""):
        monkeypatch.setenv("CDM_MAX_ANNOTATION_MIB", junk)
        with pytest.raises(ValueError, match="CDM_MAX_ANNOTATION_MIB: .*give a whole number of MiB"):
            annotation_cap()


def test_json_nested_past_the_cap_is_refused_before_the_parser_sees_it(tmp_path):
    path = tmp_path / "set_list.json"
    with pytest.raises(ValueError, match=f"nests 100000 levels deep; JSON read here may nest at most {MAX_JSON_DEPTH}"):
        parse_json(nested_json(100_000).encode(), "data.root", path)
    at_cap = "[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH
    assert parse_json(at_cap.encode(), "data.root", path) == json.loads(at_cap)
    # Brackets inside strings (escaped quotes too) are text, not nesting.
    text = json.dumps({"name": "[[[[" * 100 + '\\"' + "{{" * 100, "list": [[1]]})
    assert parse_json(text.encode(), "data.root", path)["list"] == [[1]]


def test_json_that_is_not_utf8_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "pc_dict_v2.json"
    path.write_bytes(b'{"train": "\xff\xfe"}')
    with pytest.raises(ValueError, match=f"data.root: {path} is not JSON"):
        read_json(path, "data.root")


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


@pytest.mark.parametrize(
    "path", ["../outside/x.jpg", "teddybear/../../x.jpg", "/etc/passwd", "\\\\server\\x", "C:/x", "", "a\0b"]
)
def test_an_annotation_path_leaving_the_root_is_refused(path):
    with pytest.raises(ValueError, match="^frame_annotations.jgz entry 3: image.path gives the path"):
        inside(path, "frame_annotations.jgz entry 3: image.path")


def test_an_annotation_path_below_the_root_is_kept():
    assert (
        inside("teddybear/101_11758_21048/images/frame000001.jpg", "x")
        == "teddybear/101_11758_21048/images/frame000001.jpg"
    )


@pytest.mark.parametrize("name", ["..", ".", "../../../ESCAPED", "a/b", ".hidden", "", "x" * 129, 7, None])
def test_a_name_that_is_not_one_plain_file_name_is_refused(name):
    with pytest.raises(ValueError, match="expected a plain name"):
        plain_name(name, "sequence_annotations.jgz: sequence_name")


def test_object_ids_have_three_plain_parts():
    assert object_id_parts("co3d/teddybear/101_11758_21048", "m") == ["co3d", "teddybear", "101_11758_21048"]
    for bad in ("co3d/teddybear/../../../x", "co3d/x", "co3d/a/b/c"):
        with pytest.raises(ValueError):
            object_id_parts(bad, "m")
