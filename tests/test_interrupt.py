"""Ctrl-C and SIGTERM end a command in one line, leaving no temporary file (cdm/interrupt.py, issue 49 §3)."""

from __future__ import annotations

import signal
import time

import pytest

from tests.hostile_files import start_command, stop_command


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_a_tool_part_way_in_one_line_with_no_temporary_file(signum, tmp_path):
    out = tmp_path / "views"
    proc = start_command(["-m", "cdm.tools.export_views", "--out", str(out), "--rounds", "3"])
    deadline = time.monotonic() + 120
    while sum(1 for p in out.rglob("*.png")) < 5:
        assert proc.poll() is None and time.monotonic() < deadline, "the tool wrote no view"
        time.sleep(0.05)
    code, err = stop_command(proc, signum)
    assert code == 130, err[-2000:]
    assert err.strip().splitlines() == ["interrupted: cdm-lab export-views stopped on Ctrl-C or SIGTERM"]
    assert [p.name for p in out.rglob("*") if ".tmp-" in p.name] == []
