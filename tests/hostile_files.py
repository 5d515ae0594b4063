"""Hostile files for tests, small on disk and large when read: gzip and zip bombs, lying ``.npy`` headers,
FIFOs, and a command runner that measures the peak memory of what it runs.

:func:`run_command` runs a command the way a user types it, in its own process group (a hang is killed
whole at the timeout) under a fresh interpreter whose only child is the command, so
``RUSAGE_CHILDREN`` gives that command's peak RSS and nothing else's.
"""

from __future__ import annotations

import gzip
import io
import os
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
_CHUNK = 2**24
_MEASURE = ("import resource, subprocess, sys; rc = subprocess.call(sys.argv[2:]); "
            "open(sys.argv[1], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)); sys.exit(rc)")


class Outcome(NamedTuple):
    code: int
    stdout: str
    stderr: str
    peak_rss: int
    """Bytes."""

    def error_lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.startswith("error: ")]


YAML_BOMB = "name: bomb\ngrid:\n  data.categories: &a [[x, x, x, x, x, x, x, x, x]]\n" + "".join(
    f"  {p}: &{n} [{', '.join([f'*{p}'] * 9)}]\n" for p, n in zip("abcdefg", "bcdefgh"))
"""A 330-byte alias chain: 9⁸ ≈ 43 million leaves once expanded."""


STOP_S = 5
"""Issue 49's bound on a command's end after Ctrl-C or SIGTERM, in seconds."""


def start_command(args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
    """``python *args`` started from this checkout in its own process group, its output piped, not waited on."""
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
                            start_new_session=True)


def stop_command(proc: subprocess.Popen, signum: int) -> tuple[int, str]:
    """Send ``signum``; the exit code and stderr once the command ended, failing if it outlived :data:`STOP_S`."""
    proc.send_signal(signum)
    try:
        _, err = proc.communicate(timeout=STOP_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"{signal.Signals(signum).name} did not end {proc.args[1:3]} within {STOP_S} s")
    return proc.returncode, err


def run_command(args: list[str], cwd: Path, timeout: float = 120, env: dict[str, str] | None = None) -> Outcome:
    """``python *args`` (e.g. ``["-m", "cdm", "prepare", ...]``) from ``cwd`` with this checkout first on the path."""
    rss_file = cwd / f".rss-{os.getpid()}"
    environ = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    proc = subprocess.Popen(
        [sys.executable, "-c", _MEASURE, str(rss_file), sys.executable, *args],
        cwd=cwd,
        env=environ,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    peak = int(rss_file.read_text()) * 1024
    rss_file.unlink()
    return Outcome(proc.returncode, out, err, peak)


def assert_refused(outcome: Outcome, *needles: str) -> str:
    """Exit 2, one ``error:`` line holding every needle, no traceback; returns the line."""
    assert "Traceback" not in outcome.stderr, outcome.stderr[-3000:]
    lines = outcome.error_lines()
    assert outcome.code == 2 and len(lines) == 1, (outcome.code, outcome.stderr[-3000:])
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def gzip_bomb(path: Path, gigabytes: float = 3.0) -> int:
    """A gzip of zeros (concatenated members, as gzip allows) decompressing to ``gigabytes`` GB; returns
    its size on disk (~1 MB per GB)."""
    member = gzip.compress(bytes(_CHUNK), 9)
    count = int(gigabytes * 1e9 / _CHUNK) + 1
    path.write_bytes(member * count)
    return len(member) * count


def _deflated_zeros(prefix: bytes, count: int) -> tuple[bytes, int]:
    """Raw deflate of ``prefix`` + ``count`` × 16 MiB of zeros, built from one compressed chunk repeated
    (a full flush makes each chunk's blocks independent), and the CRC-32 of the whole; ``count`` ≥ 2."""
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    first = c.compress(prefix) + c.compress(bytes(_CHUNK)) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(bytes(_CHUNK)) + c.flush(zlib.Z_FULL_FLUSH)
    crc, zeros = zlib.crc32(prefix), bytes(_CHUNK)
    for _ in range(count):
        crc = zlib.crc32(zeros, crc)
    return first + again * (count - 1) + c.flush(), crc


def npy_header(shape: tuple[int, ...], dtype: str = "<f4") -> bytes:
    """The ``.npy`` header (format 1.0) of an array of ``shape`` and ``dtype``: what ``numpy.save`` writes first."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def write_npz(path: Path, arrays: dict[str, np.ndarray], bomb: str | None = None, bomb_gigabytes: float = 1.7) -> int:
    """``numpy.savez_compressed`` of ``arrays``, plus, as member ``bomb``, a float32 vector of zeros of
    ``bomb_gigabytes`` GB compressed ~1000:1 (written without ever holding it); returns the file's size."""
    members = []
    for name, array in arrays.items():
        buffer = io.BytesIO()
        np.lib.format.write_array(buffer, np.asarray(array), allow_pickle=False)
        raw = buffer.getvalue()
        c = zlib.compressobj(9, zlib.DEFLATED, -15)
        members.append((f"{name}.npy", c.compress(raw) + c.flush(), zlib.crc32(raw), len(raw)))
    if bomb is not None:
        count = max(2, int(bomb_gigabytes * 1e9 / _CHUNK))
        header = npy_header((count * _CHUNK // 4,))
        data, crc = _deflated_zeros(header, count)
        members.append((f"{bomb}.npy", data, crc, len(header) + count * _CHUNK))
    body, directory = bytearray(), bytearray()
    for name, data, crc, size in members:
        encoded = name.encode()
        offset = len(body)
        body += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0x21, crc, len(data), size, len(encoded), 0)
        body += encoded + data
        directory += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0x21, crc, len(data), size,
                                 len(encoded), 0, 0, 0, 0, 0, offset) + encoded
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(directory), len(body), 0)
    path.write_bytes(bytes(body + directory + end))
    return path.stat().st_size


def nested_json(depth: int = 100_000) -> str:
    """A JSON text nested ``depth`` lists deep: what overflows a recursive parser."""
    return "[" * depth + "]" * depth
