"""Issue 49, hangs: a Ray address where no cluster answers is one ``error:`` line naming ``--address`` (or
``RAY_ADDRESS``) within 30 s, exit 2, nothing written; Ctrl-C and SIGTERM end a command within 5 s, whether
it is waiting on an address or writing shards, leaving no file half-written.

Unreachable addresses without a network: a port just closed on loopback, and a socket that listens (the
kernel completes every connection) but never answers, as a host that is not Ray's GCS would.
"""

from __future__ import annotations

import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sweeps.execute.local_cluster import descendants
from tests.datasets_fixtures import make_co3d
from tests.hostile_files import ROOT, assert_refused, run_command, start_command, stop_command

pytestmark = pytest.mark.slow  # each runs a command that imports torch and Ray: seconds on 2 shared cores

VERDICT_S = 30  # the bound on an unreachable address's error line
LOOPBACK = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}  # Ray joins 127.0.0.1 as itself, not the outward address


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def silent() -> Iterator[int]:
    """A port on 127.0.0.1 that accepts connections (the kernel's backlog) and never says a byte."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(16)
        yield s.getsockname()[1]


@pytest.fixture(scope="module")
def co3d(tmp_path_factory) -> Path:
    """Co3D's layout, frames ×6, so preparing it takes long enough for a signal to land part way."""
    tree = make_co3d(tmp_path_factory.mktemp("co3d"), frames=3, upscale=6, splits={"train": 20, "val": 5, "test": 1})
    (tree.root / "held_out.txt").write_text(tree.sequences["hydrant"]["val"][0])
    return tree.root


def _prepare(co3d: Path, out: Path) -> list[str]:
    return ["sweeps/inputs.py", "prepare", "--set", "data.kind=co3d", "--root", str(co3d), "--out", str(out),
            "--set", "data.image_size=32"]


@pytest.mark.parametrize("address, needle", [
    ("junk", "not a Ray address; give host:port"),
    ("ray://10.0.0.10:10001", "Ray Client addresses are not supported"),
    ("http://127.0.0.1:8265", "that is a dashboard's address, for `ray job submit`"),
    ("local", "leave --address out"),
    ("0.0.0.0:{closed}", "cannot connect (Connection refused)"),
    ("127.0.0.1:{closed}", "cannot connect (Connection refused)"),
    ("127.0.0.1:{silent}", "something listens there but nothing answered as a Ray GCS within 8 s"),
])
def test_an_address_no_cluster_answers_at_is_one_line_naming_it(address, needle, silent, co3d, tmp_path):
    address = address.format(closed=_closed_port(), silent=silent)
    out = tmp_path / "prepared"
    outcome = run_command([*_prepare(co3d, out), "--address", address], ROOT, timeout=VERDICT_S, env=LOOPBACK)
    line = assert_refused(outcome, f"--address {address}", needle)
    assert "host:port" in line and "auto" in line  # what is allowed
    assert not out.exists()  # refused before --out is made


def test_ray_address_from_the_environment_is_named_as_such(co3d, tmp_path):
    address = f"0.0.0.0:{_closed_port()}"
    outcome = run_command(_prepare(co3d, tmp_path / "prepared"), ROOT, timeout=VERDICT_S, env={"RAY_ADDRESS": address})
    assert_refused(outcome, f"RAY_ADDRESS {address}: cannot connect")


def test_a_sweep_refuses_an_unreachable_address_and_leaves_its_storage_empty(tmp_path, silent):
    storage = tmp_path / "results"
    args = ["sweeps/run.py", "sweeps/point_size.yaml", "--smoke", "--out", str(storage),
            "--tracking-uri", f"sqlite:///{tmp_path / 'mlflow.db'}"]
    junk = run_command([*args, "--address", "head:port", "--dry-run"], ROOT, timeout=VERDICT_S)
    assert_refused(junk, "--address head:port: not a Ray address")
    unreachable = run_command([*args, "--address", f"127.0.0.1:{silent}"], ROOT, timeout=VERDICT_S + 30, env=LOOPBACK)
    assert_refused(unreachable, f"--address 127.0.0.1:{silent}: something listens there but nothing answered")
    assert not storage.exists() or list(storage.rglob("*")) == []


def _wait_for(condition, what: str, limit_s: float = 120) -> None:
    deadline = time.monotonic() + limit_s
    while not condition():
        assert time.monotonic() < deadline, f"never saw {what}"
        time.sleep(0.05)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_a_command_waiting_on_a_silent_address(signum, silent, co3d, tmp_path):
    out = tmp_path / "prepared"
    proc = start_command([*_prepare(co3d, out), "--address", f"127.0.0.1:{silent}"], LOOPBACK)
    _wait_for(lambda: _connections(silent) > 0, "the command wait on the address")  # the GCS call, 8 s at most
    code, err = stop_command(proc, signum)
    assert code == 130 and "interrupted: cdm-lab inputs prepare stopped" in err, err[-2000:]
    assert "Traceback" not in err and not out.exists()


def _connections(port: int) -> int:
    """Established connections with ``port`` at either end (``/proc/net/tcp``: local, remote, state 01)."""
    rows = [r.split() for r in Path("/proc/net/tcp").read_text().splitlines()[1:]]
    return sum(1 for r in rows if r[3] == "01" and f":{port:04X}" in (r[1][-5:], r[2][-5:]))


def _counts(stdout: str) -> tuple[str, str]:
    """(written, already complete) of prepare's last line."""
    words = stdout.strip().splitlines()[-1].split()
    return words[words.index("shards") - 1], words[words.index("already") - 1]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_prepare_part_way_with_nothing_half_written(signum, co3d, tmp_path):
    out = tmp_path / "prepared"
    proc = start_command(["-m", "cdm", "prepare", "--set", "data.kind=co3d", "--root", str(co3d), "--out", str(out),
                   "--set", "data.image_size=32"])
    _wait_for(lambda: any(out.rglob("*.safetensors")), "a shard written")
    code, err = stop_command(proc, signum)
    assert code == 130 and "interrupted: cdm-lab prepare stopped" in err, err[-2000:]
    assert "Traceback" not in err
    assert [p.name for p in out.rglob("*") if ".tmp" in p.name] == []  # no temporary file left behind
    rerun = run_command(["-m", "cdm", "prepare", "--set", "data.kind=co3d", "--root", str(co3d), "--out", str(out),
                         "--set", "data.image_size=32"], ROOT)
    assert rerun.code == 0, rerun.stderr[-2000:]
    written, kept = (int(n) for n in _counts(rerun.stdout))
    assert kept >= 1 and written + kept == len(list(out.rglob("*.safetensors")))  # each shard there was whole


def _running(pid: int) -> str:
    """``pid``'s program if it runs (a zombie has ended), else ``""``."""
    try:
        if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
            return ""
        return Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
    except OSError:
        return ""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_the_local_cluster_starts_ends_within_5_s_leaving_nothing_running(signum, co3d, tmp_path):
    """Issue 55 §3: ``ray.init`` was still starting the GCS when the signal came (4.1–8.2 s before)."""
    proc = start_command(_prepare(co3d, tmp_path / "prepared"))
    seen: set[int] = set()

    def gcs_started() -> bool:
        seen.update(descendants(proc.pid))
        return any("gcs_server" in _running(pid) for pid in seen)

    _wait_for(gcs_started, "the local cluster's GCS start")
    code, err = stop_command(proc, signum)  # fails past STOP_S
    assert code == 130 and "interrupted: cdm-lab inputs prepare stopped" in err, err[-2000:]
    assert "Traceback" not in err
    deadline = time.monotonic() + 1
    while any(_running(pid) for pid in seen) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert [_running(pid) for pid in seen if _running(pid)] == []
