"""Ctrl-C and SIGTERM end a command in one line, leaving no temporary file (cdm/interrupt.py, issue 49 §3)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.hostile_files import ROOT

STOP_S = 5
"""The issue's bound: a signal ends any command within 5 s."""


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_a_tool_part_way_in_one_line_with_no_temporary_file(signum, tmp_path):
    out = tmp_path / "views"
    proc = subprocess.Popen([sys.executable, "-m", "cdm.tools.export_views", "--out", str(out), "--rounds", "3"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, start_new_session=True)
    deadline = time.monotonic() + 120
    while sum(1 for p in out.rglob("*.png")) < 5:
        assert proc.poll() is None and time.monotonic() < deadline, "the tool wrote no view"
        time.sleep(0.05)
    proc.send_signal(signum)
    try:
        _, err = proc.communicate(timeout=STOP_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"{signal.Signals(signum).name} did not end the tool within {STOP_S} s")
    assert proc.returncode == 130, err[-2000:]
    assert err.strip().splitlines() == ["interrupted: python -m cdm.tools.export_views stopped on Ctrl-C or SIGTERM"]
    assert [p.name for p in out.rglob("*") if ".tmp-" in p.name] == []
