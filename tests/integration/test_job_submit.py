"""``ray job submit`` of a smoke sweep to a real Ray head, tracked on a real MLflow server (issue 5).

Everything runs as separate processes on this machine, started the way ``cluster/README.md`` tells a
user to: ``ray start --head`` with the dashboard on 127.0.0.1 and token authentication on, and
``mlflow server --host 127.0.0.1``. The sweep is submitted with the repository's
``cluster/runtime_env.yaml``; the test polls ``ray job status`` until the job ends, then reads the
parent and child runs back from the server with ``MlflowClient``.

Clean-up never uses ``ray stop``: it kills every Ray process of the machine (it matches process
names, whatever cluster they belong to), which would take down other people's Ray sessions on a
shared host. Instead the head runs in the foreground (``--block``) in its own session with its own
``--temp-dir``, and we stop exactly the processes of that session and any process working inside
that temp dir (job drivers and workers run in the unpacked ``working_dir`` there).
"""

from __future__ import annotations

import importlib.util
import ipaddress
import math
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from docs import screenshots
from docs.screenshots import free_port, wait_http

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent  # the venv's `ray` and `mlflow` CLIs sit beside its python


def _pids_of(pgid: int, temp_dir: str | None) -> list[int]:
    """Processes in process group ``pgid``, or whose command line or working directory is in ``temp_dir``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            in_group = os.getpgid(int(entry.name)) == pgid
            if not in_group and temp_dir is not None:
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                in_group = temp_dir in cmdline or os.readlink(entry / "cwd").startswith(temp_dir)
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue  # exited meanwhile, or not ours to inspect (then not ours to stop either)
        if in_group:
            found.append(int(entry.name))
    return found


def _signal(pids: list[int], sig: signal.Signals) -> None:
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass  # already gone


def _stop(proc: subprocess.Popen, temp_dir: str | None, grace_s: float = 10.0) -> None:
    """SIGTERM ``proc``'s process group and every process tied to ``temp_dir``; SIGKILL what is left.

    ``proc`` was started with ``start_new_session=True``, so its group holds it and its children
    and nothing of ours; Ray job drivers get sessions of their own but work inside ``temp_dir``.
    """
    _signal(_pids_of(proc.pid, temp_dir), signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and (proc.poll() is None or _pids_of(proc.pid, temp_dir)):
        time.sleep(0.2)
    _signal(_pids_of(proc.pid, temp_dir), signal.SIGKILL)
    proc.wait(timeout=10)


def _http_status(url: str, headers: dict[str, str] | None = None) -> int:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=5) as resp:
            return resp.status
    except urllib.error.HTTPError as exc:
        return exc.code


def _listening_on(port: int) -> set[str]:
    """Local addresses with a TCP socket listening on ``port``, read from /proc (no traffic sent)."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, hex_port = local.split(":")
            if state != "0A" or int(hex_port, 16) != port:  # 0A = LISTEN
                continue
            raw = bytes.fromhex(addr)
            # The kernel prints each 32-bit word in host (little-endian) order.
            words = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
            found.add(str(ipaddress.ip_address(words)))
    return found


@dataclass(frozen=True)
class Head:
    dashboard: str  # http://127.0.0.1:<port>
    dashboard_port: int
    env: dict[str, str]  # token, PATH: what every `ray` CLI call against this head needs
    temp_dir: str


@pytest.fixture(scope="module")
def ray_head() -> Iterator[Head]:
    """A one-node Ray head (2 CPUs, dashboard on 127.0.0.1, token auth on) for this module's tests, stopped
    afterwards."""
    # Without ray[default] the dashboard starts in minimal mode with no HTTP server, so no job can
    # be submitted: say so instead of timing out.
    missing = [m for m in ("aiohttp_cors", "grpc", "opencensus") if importlib.util.find_spec(m) is None]
    assert not missing, f"`ray job submit` needs ray[default] (missing {missing}): pip install 'ray[default]'"
    # Short path: Ray's unix sockets live under the temp dir and must stay under ~107 characters.
    temp_dir = tempfile.mkdtemp(prefix="cdmray", dir="/tmp")
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",  # the job's `python` is this venv's
        # A token made for this head only: never read or overwrite the user's ~/.ray/auth_token.
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(32),
        "RAY_USAGE_STATS_ENABLED": "0",
        "PYTHONUNBUFFERED": "1",  # `ray start`'s lines reach its log (read below) as they are printed
    }
    env.pop("RAY_ADDRESS", None)
    dash = free_port()
    # Every port with a fixed default gets a free one, so two heads on one host never collide.
    cmd = [str(BIN / "ray"), "start", "--head", "--block", "--node-ip-address", "127.0.0.1",
           "--port", str(free_port()), "--dashboard-host", "127.0.0.1", "--dashboard-port", str(dash),
           "--dashboard-agent-listen-port", str(free_port()),
           "--num-cpus", "2", "--num-gpus", "0", "--temp-dir", temp_dir, "--disable-usage-stats"]
    log = Path(temp_dir) / "ray_start.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        auth = {"Authorization": f"Bearer {env['RAY_AUTH_TOKEN']}"}
        wait_http(f"http://127.0.0.1:{dash}/api/version", proc, log, auth)
        # The job API needs the head's dashboard agent too; it is up once jobs can be listed.
        wait_http(f"http://127.0.0.1:{dash}/api/jobs/", proc, log, auth)
        yield Head(f"http://127.0.0.1:{dash}", dash, env, temp_dir)
    finally:
        _stop(proc, temp_dir)
        shutil.rmtree(temp_dir, ignore_errors=True)


@contextmanager
def serve_mlflow(store: Path, grace_s: float = 10.0) -> Iterator[str]:
    """``mlflow server`` on 127.0.0.1 with a SQLite backend and proxied artifacts in ``store``; its URL."""
    store.mkdir(parents=True, exist_ok=True)
    # Clients upload through the server (mlflow-artifacts:/), so trials on any node reach it.
    with screenshots.mlflow_server(
        f"sqlite:///{store / 'mlflow.db'}", store / "server.log", artifacts=store / "artifacts", grace_s=grace_s
    ) as url:
        yield url


@pytest.fixture(scope="module")
def mlflow_store(tmp_path_factory) -> Path:
    """Where the module's ``mlflow server`` keeps its runs and the artifacts uploaded through it."""
    return tmp_path_factory.mktemp("mlflow_server")


@pytest.fixture(scope="module")
def mlflow_server(mlflow_store) -> Iterator[str]:
    with serve_mlflow(mlflow_store) as url:
        yield url


def _ray_job(head: Head, verb: str, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """``ray job VERB --address <dashboard> ARGS`` against ``head``, with its token in the environment."""
    # Plain records: no colours or boxes in the output parsed below.
    cmd = [str(BIN / "ray"), "job", verb, "--address", head.dashboard, "--log-style", "record", *args]
    # check=False: callers assert on the return code with the output in the message.
    return subprocess.run(cmd, check=False, env=head.env, cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def _job_status(cli_output: str, sub_id: str) -> str:
    """The job's state from ``ray job status`` output (2.60 words end states, prints the others)."""
    ends = {"succeeded": "SUCCEEDED", "failed": "FAILED", "was stopped": "STOPPED"}
    for words, state in ends.items():
        if f"Job '{sub_id}' {words}" in cli_output:
            return state
    found = re.search(rf"Status for job '{re.escape(sub_id)}': (\w+)", cli_output)
    assert found, f"unexpected `ray job status` output:\n{cli_output}"
    return found.group(1)


def test_head_binds_loopback_and_requires_the_token(ray_head, mlflow_server):
    auth = {"Authorization": f"Bearer {ray_head.env['RAY_AUTH_TOKEN']}"}
    assert _http_status(f"{ray_head.dashboard}/api/jobs/") == 401  # no token: refused
    assert _http_status(f"{ray_head.dashboard}/api/jobs/", {"Authorization": "Bearer wrong"}) == 403
    assert _http_status(f"{ray_head.dashboard}/api/jobs/", auth) == 200
    # Ray turns --node-ip-address 127.0.0.1 into the host's outward IP (resolve_ip_for_localhost),
    # and its GCS and raylet listen on all interfaces in 2.60 (the token guards them); the dashboard
    # and MLflow must listen on loopback only.
    assert _listening_on(ray_head.dashboard_port) == {"127.0.0.1"}
    assert _listening_on(int(mlflow_server.rsplit(":", 1)[1])) == {"127.0.0.1"}


def test_submitted_smoke_sweep_logs_parent_and_children_to_the_server(ray_head, mlflow_server, mlflow_store, tmp_path):
    from mlflow import MlflowClient

    from sweeps.store.read import last_eval_files

    storage = tmp_path / "results"
    sub_id = f"cdm-smoke-{secrets.token_hex(4)}"
    t0 = time.monotonic()
    submit = _ray_job(ray_head, "submit", "--working-dir", ".",
                  "--runtime-env", "cluster/runtime_env.yaml", "--submission-id", sub_id, "--no-wait", "--",
                  "python", "sweeps/run.py", "sweeps/point_size.yaml", "--smoke",
                  "--out", str(storage), "--tracking-uri", mlflow_server)
    assert submit.returncode == 0, submit.stdout + submit.stderr
    status = "PENDING"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        out = _ray_job(ray_head, "status", sub_id)
        assert out.returncode == 0, out.stdout + out.stderr
        status = _job_status(out.stdout, sub_id)
        if status in ("SUCCEEDED", "FAILED", "STOPPED"):
            break
        time.sleep(4)
    wall = time.monotonic() - t0
    logs = _ray_job(ray_head, "logs", sub_id).stdout
    assert status == "SUCCEEDED", f"job {sub_id} ended {status} after {wall:.0f} s; its log:\n{logs[-6000:]}"
    print(f"\nsubmitted smoke sweep: {wall:.1f} s from submit to SUCCEEDED")
    assert "profile in force: smoke" in logs and f"MLflow: {mlflow_server}" in logs

    client = MlflowClient(mlflow_server)
    exp = client.get_experiment_by_name("point_size")
    assert exp is not None
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if r.data.tags.get("kind") == "sweep"]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    parent = parents[0]
    assert {a.path for a in client.list_artifacts(parent.info.run_id)} >= {
        "point_size.yaml",
        "plan.json",
        "results.md",
        "results.csv",
    }
    # One child per trial: the 5 point sizes of the spec, one seed.
    assert sorted(c.data.params["priors.point_size"] for c in children) == ["0.0075", "0.01", "0.02", "0.04", "0.08"]
    assert len({c.data.tags["trial_id"] for c in children}) == 5
    for child in children:
        assert child.info.status == "FINISHED"
        assert child.data.tags["mlflow.parentRunId"] == parent.info.run_id
        assert [m.step for m in client.get_metric_history(child.info.run_id, "eval/cd")] in ([10, 20], [20, 10])
        files = last_eval_files(client, child.info.run_id)  # eval/step_0000020/{panels,clouds}/
        assert any(f.endswith(".ply") for f in files) and any(f.endswith(".png") for f in files)
        assert "config.yaml" in {a.path for a in client.list_artifacts(child.info.run_id)}
    # Artifacts went through the server into its own store, not into the job's working directory.
    stored = list((mlflow_store / "artifacts").rglob("*.ply"))
    assert len(stored) >= 5
    assert all(math.isfinite(c.data.metrics["eval/cd"]) for c in children)
    assert (storage / "point_size" / "smoke" / "results.md").is_file()
