"""cdm/io/files.py: regular files only, whole reads and gunzipping bounded before anything is allocated."""

from __future__ import annotations

import os
import resource

import pytest

from cdm.io.files import (
    annotation_cap,
    file_sha256,
    open_regular,
    read_bounded,
    read_from,
    read_gzip,
    read_text,
    sha256_from,
)
from tests.hostile_files import gzip_bomb


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
    assert read_text(tmp_path / "link.json", "field") == '{"a": [1, 2]}'


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


def test_read_text_is_utf8_or_one_line_naming_the_file(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("héllo\n")
    assert read_text(path, "notes") == "héllo\n"
    path.write_bytes(b"\xff\xfe x")
    with pytest.raises(ValueError, match=f"^notes: {path} is not UTF-8 text \\(byte 0\\)$"):
        read_text(path, "notes")
    with pytest.raises(ValueError, match="is 4 bytes; at most 3 are read"):
        read_text(path, "notes", cap=3)


def test_file_sha256_is_hashlibs_of_the_bytes_and_refuses_a_fifo(tmp_path):
    import hashlib

    path = tmp_path / "weights.bin"
    path.write_bytes(b"x" * (3 * 2**20 + 5))  # more than one 1 MiB chunk
    assert file_sha256(path, "model.encoder_weights") == hashlib.sha256(path.read_bytes()).hexdigest()
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(ValueError, match="is a FIFO"):
        file_sha256(tmp_path / "fifo", "model.encoder_weights")


def test_a_file_in_a_pyarrow_file_system_is_read_within_the_same_caps(tmp_path):
    # A sweep folder in an object store is read through pyarrow; file:// stands in for s3:// here.
    from pyarrow import fs

    path = tmp_path / "sweep.json"
    path.write_text('{"profile": "smoke"}')
    assert read_text(path.as_uri(), "--resume") == '{"profile": "smoke"}'
    with pytest.raises(ValueError, match=r"--resume: .*sweep.json is 20 bytes; at most 8 are read"):
        read_bounded(path.as_uri(), "--resume", cap=8)
    local = fs.LocalFileSystem()
    assert sha256_from(local, str(path), "--resume") == file_sha256(path, "--resume")
    with pytest.raises(ValueError, match="missing.json does not exist"):
        read_from(local, str(tmp_path / "missing.json"), "--resume")
    os.mkfifo(tmp_path / "fifo")  # no writer: opening it as a stream would block
    with pytest.raises(ValueError, match="fifo is not a regular file"):
        read_from(local, str(tmp_path / "fifo"), "--resume")
