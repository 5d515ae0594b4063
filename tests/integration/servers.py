"""Helpers for the integration tests that start a real server (mlflow server, Ray's head, moto's S3)."""

from __future__ import annotations

import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

STARTUP_S = 240.0
"""How long a server of these tests may take to answer. On a loaded 2-core machine (load average
13, test processes under ``nice``) ``mlflow server`` first answered ``/health`` 43 s after it was
started, and that first answer took 2.3 s; a 60-s wait has run out under the full suite."""


def free_port() -> int:
    """A TCP port free on every interface (Ray's GCS and raylet listen on all of them in Ray 2.60)."""
    with socket.socket() as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def wait_http(url: str, proc: subprocess.Popen, log: Path, headers: dict[str, str] | None = None,
              timeout_s: float = STARTUP_S) -> None:
    """Poll ``url`` until it answers 200; fail early with the log if the server process died."""
    t0 = time.monotonic()
    last = "no answer yet"
    while time.monotonic() - t0 < timeout_s:
        assert proc.poll() is None, f"server exited with {proc.returncode}:\n{log.read_text()[-3000:]}"
        try:
            # A long read timeout: a slow first answer abandoned would only queue the next request behind it.
            with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=30) as resp:
                if resp.status == 200:
                    return
                last = f"HTTP {resp.status}"
        except urllib.error.HTTPError as exc:
            last = f"HTTP {exc.code}"
        except (urllib.error.URLError, ConnectionError, TimeoutError) as exc:
            last = repr(exc)  # not listening yet, or busy starting
        time.sleep(0.5)
    pytest.fail(f"{url} did not answer within {timeout_s:.0f} s (last: {last}); server log:\n{log.read_text()[-3000:]}")
