"""A sweep's outer boundaries on real parts: an S3 API, the sockets of its own local Ray, its folder claim.

The object store is ``moto``'s S3 server on 127.0.0.1 with IAM authentication on (a wrong secret is
refused as by AWS); the runner reaches it the way a user's shell would, through
``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``/``AWS_ENDPOINT_URL``. One sweep serves several
checks: two copies are started together (one must refuse: the folder is claimed), the survivor's
listening sockets are read from ``/proc/net/tcp{,6}`` and matched to its processes (every one must be
loopback), its driver is SIGKILLed mid-trial, and ``--resume`` ends the killed cluster's leftovers,
finishes the sweep in S3 with each trial once in MLflow.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import ray
from mlflow import MlflowClient

from docs.screenshots import free_port, wait_http
from sweeps import run
from sweeps.execute.local_cluster import SESSION_RECORDS, session_pids
from sweeps.execute.precompute import shared_bytes
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from sweeps.results.view import BASELINE_KIND
from tests.test_trust import small_disk

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
BUCKET = "cdm-sweeps"


@pytest.fixture(scope="module")
def s3(tmp_path_factory) -> Iterator[dict[str, str]]:
    """moto's S3 server on 127.0.0.1 with IAM auth; yields the environment of a user with a bucket."""
    import boto3

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    log = tmp_path_factory.mktemp("moto") / "server.log"
    # The first 4 requests (user, policy, attachment, key) may go unsigned; every later one is checked.
    with log.open("w") as out:
        server = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                                  env={**os.environ, "INITIAL_NO_AUTH_ACTION_COUNT": "4"},
                                  stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_http(f"{url}/moto-api/", server, log)
        setup = dict(
            endpoint_url=url, region_name="us-east-1", aws_access_key_id="setup", aws_secret_access_key="setup"
        )
        iam = boto3.client("iam", **setup)
        iam.create_user(UserName="cdm")
        policy = iam.create_policy(PolicyName="s3-all", PolicyDocument=json.dumps(
            {"Version": "2012-10-17", "Statement": [{"Effect": "Allow", "Action": "s3:*", "Resource": "*"}]}))
        iam.attach_user_policy(UserName="cdm", PolicyArn=policy["Policy"]["Arn"])
        key = iam.create_access_key(UserName="cdm")["AccessKey"]
        env = {"AWS_ACCESS_KEY_ID": key["AccessKeyId"], "AWS_SECRET_ACCESS_KEY": key["SecretAccessKey"],
               "AWS_ENDPOINT_URL": url, "AWS_DEFAULT_REGION": "us-east-1"}
        boto3.client("s3", endpoint_url=url, region_name="us-east-1", aws_access_key_id=env["AWS_ACCESS_KEY_ID"],
                     aws_secret_access_key=env["AWS_SECRET_ACCESS_KEY"]).create_bucket(Bucket=BUCKET)
        yield env
    finally:
        os.killpg(server.pid, signal.SIGKILL)
        server.wait()


def _address(table: str, hex_addr: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    raw = bytes.fromhex(hex_addr)
    if table == "tcp":
        return ipaddress.IPv4Address(raw[::-1])
    # /proc/net/tcp6 prints the 16 bytes as four host-order 32-bit words.
    address = ipaddress.IPv6Address(b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))
    return address.ipv4_mapped or address


def listening_sockets(pids: set[int]) -> list[tuple[int, str, int]]:
    """(pid, address, port) of every TCP socket in LISTEN state held by one of ``pids``."""
    listening: dict[int, tuple[str, int]] = {}
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A":  # TCP_LISTEN
                hex_addr, hex_port = fields[1].split(":")
                listening[int(fields[9])] = (str(_address(table, hex_addr)), int(hex_port, 16))
    found = []
    for pid in pids:
        try:
            links = [os.readlink(fd) for fd in Path(f"/proc/{pid}/fd").iterdir()]
        except OSError:
            continue
        inodes = {int(link[8:-1]) for link in links if link.startswith("socket:[")}
        found += [(pid, *listening[i]) for i in inodes & listening.keys()]
    return found


def descendants(root: int) -> set[int]:
    children: dict[int, set[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, set()).add(int(stat.parent.name))
    out, todo = set(), [root]
    while todo:
        pid = todo.pop()
        out.add(pid)
        todo += children.get(pid, set()) - out
    return out


def _s3_files(env: dict[str, str], prefix: str) -> list[str]:
    from pyarrow import fs

    store = fs.S3FileSystem(access_key=env["AWS_ACCESS_KEY_ID"], secret_key=env["AWS_SECRET_ACCESS_KEY"],
                            endpoint_override=env["AWS_ENDPOINT_URL"], region="us-east-1")
    infos = store.get_file_info(fs.FileSelector(f"{BUCKET}/{prefix}", recursive=True, allow_not_found=True))
    return [i.path for i in infos if i.type == fs.FileType.File]


def _alive(pids: set[int]) -> set[int]:
    return {
        p
        for p in pids
        if Path(f"/proc/{p}").exists() and "Z" not in Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1][:3]
    }


def test_s3_sweep_is_claimed_listens_on_loopback_and_resumes_after_a_kill(s3, tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: s3kill\ngrid: {priors.point_size: [0.02, 0.04]}\nresources: {max_concurrent_trials: 1}\n"
                    "profiles: {smoke: {budget: {steps: 60, eval_every: 10}}}\n")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    storage = f"s3://{BUCKET}/results"
    argv = [sys.executable, str(ROOT / "sweeps" / "run.py"), str(spec), "--smoke", "--out", storage,
            "--tracking-uri", uri]
    env = {**os.environ, **s3, "PYTHONPATH": str(ROOT), "XDG_STATE_HOME": str(tmp_path / "state")}
    env.pop("RAY_ADDRESS", None)
    logs = [tmp_path / "a.log", tmp_path / "b.log"]
    copies = [
        subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT) for log in logs
    ]
    try:
        deadline = time.monotonic() + 120
        while all(c.poll() is None for c in copies):
            assert time.monotonic() < deadline, "neither copy was refused"
            time.sleep(0.1)
        refused = next(i for i, c in enumerate(copies) if c.poll() is not None)
        driver = copies[1 - refused]
        text = logs[refused].read_text()
        assert copies[refused].returncode == 2, text
        assert "a sweep is already running there" in text and f"{storage}/s3kill/smoke" in text, text
        assert "Traceback" not in text and len([ln for ln in text.splitlines() if ln.startswith("error:")]) == 1

        # Wait until the first trial has checkpointed into S3 three times: the cluster, its agents and a
        # worker are all up, and Tune's state (synced each second) knows a checkpoint to resume from.
        deadline = time.monotonic() + 300
        while not any("/trial_" in p and "/checkpoint_000002/" in p for p in _s3_files(s3, "results/s3kill/smoke")):
            assert driver.poll() is None and time.monotonic() < deadline, logs[1 - refused].read_text()[-3000:]
            time.sleep(0.5)
        record = json.loads((SESSION_RECORDS / f"{driver.pid}.json").read_text())
        pids = descendants(driver.pid) | session_pids(record["session_dir"])
        sockets = listening_sockets(pids)
        # GCS, raylet (node manager + object manager), driver, worker, two agents, metrics servers.
        assert len(sockets) >= 6, sockets
        exposed = [s for s in sockets if not ipaddress.ip_address(s[1]).is_loopback]
        assert not exposed, f"listening beyond loopback (pid, address, port): {exposed}"

        driver.send_signal(signal.SIGKILL)
        driver.wait()
    finally:
        for c in copies:
            if c.poll() is None:
                c.kill()
                c.wait()
    leftovers = _alive(session_pids(record["session_dir"]))

    # A killed driver recorded no digest of Tune's state (pickles) in the bucket: the resume says so and
    # how to vouch for the bucket, and unpickles nothing.
    refused = subprocess.run([*argv, "--resume"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stdout[-3000:] + refused.stderr[-3000:]
    assert "no digest of" in refused.stderr and "--trust-storage" in refused.stderr, refused.stderr
    resumed = subprocess.run([*argv, "--resume", "--trust-storage"], cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=600)
    (tmp_path / "resumed.log").write_text(resumed.stdout + resumed.stderr)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    if leftovers:
        assert "leftover Ray processes of an earlier sweep" in resumed.stdout
    assert not _alive(leftovers), f"processes of the killed sweep still alive: {_alive(leftovers)}"
    assert "resuming from" in resumed.stdout, resumed.stdout[-3000:]
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("s3kill").experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(children) == 2 and all(c.info.status == "FINISHED" for c in children)
    for child in children:
        steps = [m.step for m in client.get_metric_history(child.info.run_id, "train/loss")]
        assert sorted(steps) == list(range(5, 61, 5)), (child.info.run_name, steps)
    stored = set(_s3_files(s3, "results/s3kill/smoke"))
    assert {f"{BUCKET}/results/s3kill/smoke/{name}" for name in ("sweep.json", "results.md", "results.csv")} <= stored
    # Six checkpoints per trial were written; the finished sweep keeps each trial's newest two.
    per_trial: dict[str, set[str]] = {}
    for found in filter(None, (re.search(r"/(trial_[^/]+)/(checkpoint_[^/]+)/", p) for p in stored)):
        per_trial.setdefault(found[1], set()).add(found[2])
    assert list(per_trial.values()) == [{"checkpoint_000004", "checkpoint_000005"}] * 2, per_trial


@pytest.mark.parametrize("change,needle", [
    ({"AWS_SECRET_ACCESS_KEY": "not-the-secret"}, "cannot write to bucket"),
    ({}, "does not exist"),
])
def test_s3_bad_credentials_or_missing_bucket_fail_before_ray(s3, tmp_path, monkeypatch, capsys, change, needle):
    for key, value in {**s3, **change}.items():
        monkeypatch.setenv(key, value)
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: s3bad\ngrid: {priors.point_size: [0.02]}\n")
    bucket = BUCKET if change else "no-such-bucket"
    code = run.main([str(spec), "--smoke", "--out", f"s3://{bucket}/results", "--tracking-uri", f"sqlite:///{tmp_path}/mlflow.db"])
    err = capsys.readouterr().err
    assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not ray.is_initialized()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]  # no MLflow store, nothing else


def test_a_disk_that_fills_mid_run_is_said_as_such_and_the_shared_cache_removed(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)  # MLflow's artifacts of a sqlite:/// store go to ./mlartifacts
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: full\ngrid: {priors.point_size: [0.04]}\n")
    need = shared_bytes(expand(load_spec(spec), "smoke"))
    # Passes the check before Ray (free >= the estimate); the lock, sweep.json, plan.json and the files'
    # own overhead then fill it while the views are written.
    size_kib = (need // 4096 + 4) * 4
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    with small_disk(tmp_path / "disk", f"{size_kib}k") as disk:
        code = run.main([str(spec), "--smoke", "--out", str(disk), "--tracking-uri", uri])
        err = capfd.readouterr().err
        errors = [line for line in err.splitlines() if line.startswith("error:")]
        assert code == 2 and len(errors) == 1, err[-3000:]
        assert errors[0].startswith(
            f"error: no space left on the device of {disk}/full/smoke (removed the shared cache "
            f"{disk}/full/smoke/shared)"
        ), errors[0]
        assert errors[0].endswith(f"--profile smoke --out {disk} --resume"), errors[0]
        assert not (disk / "full" / "smoke" / "shared").exists() and (disk / "full" / "smoke" / "sweep.json").exists()
    assert not ray.is_initialized()
    client = MlflowClient(uri)
    parents = [r for r in client.search_runs([client.get_experiment_by_name("full").experiment_id])
               if "mlflow.parentRunId" not in r.data.tags]
    assert [r.info.status for r in parents] == ["FAILED"]


@pytest.mark.parametrize(
    "stop", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"]
)  # Ctrl-C; kill, a scheduler
def test_a_stopped_driver_closes_the_interrupted_child_as_killed_and_the_hint_keeps_the_storage(tmp_path, stop):
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: sigint\ngrid: {priors.point_size: [0.02, 0.04]}\nresources: {max_concurrent_trials: 1}\n"
                    "profiles: {smoke: {budget: {steps: 400, eval_every: 10}}}\n")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    storage = tmp_path / "my results"
    argv = [sys.executable, str(ROOT / "sweeps" / "run.py"), str(spec), "--smoke", "--out", str(storage),
            "--tracking-uri", uri]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "XDG_STATE_HOME": str(tmp_path / "state")}
    env.pop("RAY_ADDRESS", None)
    log = tmp_path / "driver.log"
    driver = subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300
        while "step 20/" not in log.read_text():  # a trial is running and has logged to its child run
            assert driver.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.2)
        driver.send_signal(stop)
        driver.wait(timeout=300)
    finally:
        if driver.poll() is None:
            driver.kill()
            driver.wait()
    out = log.read_text()
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("sigint").experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert children and all(c.info.status == "KILLED" for c in children), [
        (c.info.run_name, c.info.status) for c in children
    ]
    # The parent is KILLED; the runs view's baseline rows (finished scores, no trials) are no runs of it.
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags and r.data.tags.get("kind") != BASELINE_KIND]
    assert [r.info.status for r in parents] == ["KILLED"]
    assert f"--profile smoke --out '{storage}' --resume" in out, out[-3000:]
