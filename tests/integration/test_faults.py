"""Faults on a real two-machine Ray cluster: a lost node, a killed Train worker, a killed driver (issue 5).

The cluster is ``ray.cluster_utils.Cluster``: a head on 127.0.0.1 and a worker node on 127.0.0.2,
1 CPU each. Both addresses are this machine's loopback, but Ray sees two hosts, as on a real
cluster: the runner refuses a SQLite MLflow store there, so trials log to a real ``mlflow server``
on 127.0.0.1. Storage is a local folder (one machine: every node sees it, as a shared file system)
or a ``file://`` URI, read and written through pyarrow as an object store would be.

Each fault hits a trial mid-run, after it has checkpointed; then the sweep must finish with each
trial exactly once in MLflow, its ``train/loss`` history free of repeated steps, and the
interrupted trial continuing from its checkpoint (it prints "resuming from" and its next step is
past that checkpoint, not step 5). ``failure.max_retries`` in the spec drives both retry levels:
Tune restarts a trial whose actor died with its node, Ray Train restarts a trial's dead worker.

Clean-up: the cluster's own ``shutdown()`` (never ``ray stop``: it kills every Ray process of the
machine), and the MLflow server's and the driver's process groups.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import ray
from mlflow import MlflowClient

from sweeps import run
from tests.integration.test_job_submit import _stop, serve_mlflow

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
WORKER_IP = "127.0.0.2"


class TwoMachines:
    """The cluster and what a test needs to break it and to mend it again."""

    def __init__(self, cluster, temp_dir: str):
        self.cluster, self.temp_dir = cluster, temp_dir

    def worker(self):
        return next(n for n in self.cluster.worker_nodes if n.node_ip_address == WORKER_IP)

    def ensure_worker(self) -> None:
        """Bring the worker node back if a test took it away."""
        if not any(n["Alive"] and n["NodeManagerAddress"] == WORKER_IP for n in ray.nodes()):
            self.cluster.add_node(num_cpus=1, node_ip_address=WORKER_IP, temp_dir=self.temp_dir)
            self.cluster.wait_for_nodes()


@pytest.fixture(scope="module")
def machines() -> Iterator[TwoMachines]:
    from ray.cluster_utils import Cluster

    temp_dir = tempfile.mkdtemp(prefix="cdmft", dir="/tmp")  # short: Ray's socket paths must fit ~107 chars
    # ray#59110 workaround, as in test_multinode.py: keep the loopback GCS address as given.
    patch = pytest.MonkeyPatch()
    patch.setattr(ray._private.ray_constants, "ENABLE_RAY_CLUSTER", False)
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "node_ip_address": "127.0.0.1", "temp_dir": temp_dir, "include_dashboard": False,
        # The GCS declares a silent node dead after 5 missed 3-s health checks by default; 3 × 1 s
        # keeps the lost-node test short without changing what happens after.
        "_system_config": {"health_check_period_ms": 1000, "health_check_failure_threshold": 3}})
    try:
        cluster.add_node(num_cpus=1, node_ip_address=WORKER_IP, temp_dir=temp_dir)
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, logging_level="WARNING")
        assert sorted(n["NodeManagerAddress"] for n in ray.nodes() if n["Alive"]) == ["127.0.0.1", WORKER_IP]
        yield TwoMachines(cluster, temp_dir)
    finally:
        ray.shutdown()
        cluster.shutdown()  # stops exactly the processes of these nodes
        patch.undo()
        shutil.rmtree(temp_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def mlflow_http(tmp_path_factory) -> Iterator[str]:
    """``mlflow server`` on 127.0.0.1 (SQLite backend, proxied artifacts), as cluster/README.md starts it."""
    # uvicorn waits on the clients' idle keep-alive connections before it exits: do not wait long.
    with serve_mlflow(tmp_path_factory.mktemp("mlflow_server"), grace_s=2) as url:
        yield url


def _argv(tmp_path: Path, body: str, tracking_uri: str, storage: str | None = None) -> list[str]:
    spec = tmp_path / "spec.yaml"
    spec.write_text(body)
    return [str(spec), "--smoke", "--out", storage or str(tmp_path / "results"), "--tracking-uri", tracking_uri]


def _children(uri: str, experiment: str) -> list:
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return []
    return [r for r in client.search_runs([exp.experiment_id]) if "mlflow.parentRunId" in r.data.tags]


def _tune_checkpoints(trial_dir: Path) -> int:
    """Checkpoints a Tune trial has reported (older ones get pruned: count by their index)."""
    return max((int(p.name.rsplit("_", 1)[1]) + 1 for p in trial_dir.glob("checkpoint_*") if p.is_dir()), default=0)


def _train_checkpoints(run_dir: Path) -> int:
    """Reports (each with a checkpoint) a Ray Train run has registered: it keeps only the newest two
    folders, so count from its checkpoint manager's snapshot."""
    try:
        return json.loads((run_dir / "checkpoint_manager_snapshot.json").read_text())["current_report_index"]
    except (FileNotFoundError, json.JSONDecodeError):  # not written yet, or caught mid-write
        return 0


def _assert_each_trial_once(uri: str, experiment: str, trials: int, steps: int) -> list:
    """Each trial one FINISHED child run whose train/loss history holds every logged step once."""
    client = MlflowClient(uri)
    children = _children(uri, experiment)
    assert len(children) == trials and len({c.data.tags["trial_id"] for c in children}) == trials
    for child in children:
        assert child.info.status == "FINISHED", child.info.run_name
        logged = [m.step for m in client.get_metric_history(child.info.run_id, "train/loss")]
        assert sorted(logged) == list(range(5, steps + 1, 5)), (child.info.run_name, sorted(logged))
    return children


def _assert_continued(after: list[int], every: int, steps: int) -> None:
    """The resumed trial went on from a checkpoint (one per evaluation), not from step 0, to the end.

    Its first step is one log interval (5) past a checkpoint's step. Which checkpoint depends on
    how far Ray had registered them when the fault hit (Train registers at its 2 s health check).
    """
    assert after and after[-1] == steps, after
    assert after[0] > every and (after[0] - 5) % every == 0, after[:3]


def _steps_after_resume(out: str, label: str) -> list[int]:
    """Steps the trial ``label`` printed after its (single) "resuming from" line."""
    resumed = out.split(f"[{label}] resuming from", 1)[1]
    return [int(s) for s in re.findall(rf"\[{re.escape(label)}\] step (\d+)/", resumed)]


def _sweep_with_fault(argv: list[str], ready: Callable[[], bool], fault: Callable[[], None]) -> tuple[int, bool, float]:
    """Run the sweep in this thread while another injects ``fault`` once ``ready()`` holds.

    Returns the runner's exit code, whether the fault was injected (not if the sweep ended first)
    and the wall time. An exception in the other thread is raised here by ``result()``.
    """
    def watch() -> bool:
        while not finished:
            if ready():
                fault()
                return True
            time.sleep(0.2)
        return False

    finished = False
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=1) as pool:
        injected = pool.submit(watch)
        try:
            code = run.main(argv)
        finally:
            finished = True  # the watcher stops polling even if the sweep raised
        return code, injected.result(timeout=30), time.perf_counter() - t0


def test_sqlite_store_is_refused_on_two_machines(machines, tmp_path, capsys):
    db = tmp_path / "mlflow.db"
    argv = _argv(tmp_path, "name: lite\ngrid: {priors.point_size: [0.04]}\n", f"sqlite:///{db}")
    assert run.main(argv) == 2
    err = capsys.readouterr().err
    assert "this cluster spans (or may grow to) 2 machines" in err and "mlflow server --host <private ip>" in err
    assert not db.exists() and not (tmp_path / "results").exists()


def test_autoscaler_bounds_count_as_what_a_remote_cluster_could_offer(machines):
    from ray.core.generated import autoscaler_pb2
    from ray.experimental.internal_kv import _internal_kv_del, _internal_kv_put

    from sweeps.execute.cluster import cluster_capacity, cluster_machines

    # The record an autoscaler keeps in the GCS (what Ray Data reads): up to 4 nodes of 2 GPUs each.
    config = autoscaler_pb2.ClusterConfig(node_group_configs=[
        autoscaler_pb2.NodeGroupConfig(name="gpu", resources={"CPU": 8, "GPU": 2}, min_count=0, max_count=4)])
    key, namespace = (
        ray._raylet.GCS_AUTOSCALER_CLUSTER_CONFIG_KEY.encode(),
        ray._raylet.GCS_AUTOSCALER_STATE_NAMESPACE.encode(),
    )
    assert cluster_capacity(remote=True) == {"CPU": 2, "GPU": 0}  # none published: the nodes up
    assert cluster_machines(remote=True) == 2
    _internal_kv_put(key, config.SerializeToString(), namespace=namespace)
    try:
        assert cluster_capacity(remote=True) == {"CPU": 32, "GPU": 8}
        assert cluster_capacity(remote=False) == {"CPU": 2, "GPU": 0}  # a local cluster counts what it has
        assert cluster_machines(remote=True) == 4  # a SQLite store is refused before the GPU nodes exist
    finally:
        _internal_kv_del(key, namespace=namespace)


def test_lost_node_trial_resumes_from_its_checkpoint_on_the_other(machines, mlflow_http, tmp_path, capfd):
    machines.ensure_worker()
    steps, every = 140, 20
    argv = _argv(tmp_path, f"""
name: node_loss
grid: {{priors.point_size: [0.02, 0.04]}}
failure: {{max_retries: 1}}
profiles: {{smoke: {{budget: {{steps: {steps}, eval_every: {every}}}}}}}
""", mlflow_http)
    folder = tmp_path / "results" / "node_loss" / "smoke"

    def both_checkpointed() -> bool:  # one trial per node (1 CPU each), each past its third checkpoint
        trials = list(folder.glob("trial_*"))
        return len(trials) == 2 and all(_tune_checkpoints(t) >= 3 for t in trials)

    # allow_graceful=False: SIGKILL every process of the node, as when a machine is lost.
    code, injected, wall = _sweep_with_fault(
        argv, both_checkpointed, lambda: machines.cluster.remove_node(machines.worker(), allow_graceful=False)
    )
    out = capfd.readouterr().out
    assert injected, f"the sweep ended before both trials checkpointed three times:\n{out[-3000:]}"
    assert code == 0, out[-3000:]
    print(f"\nnode loss: {wall:.1f} s")

    # The trial of the lost node restarted once (Tune), on the head, from its checkpoint.
    resumed = re.findall(r"\[(.+?)\] resuming from", out)
    assert len(resumed) == 1, out[-3000:]
    after = _steps_after_resume(out, resumed[0])
    _assert_continued(after, every, steps)
    assert "(2/2 trials done)" in out
    _assert_each_trial_once(mlflow_http, "node_loss", trials=2, steps=steps)


def test_killed_train_worker_resumes_from_its_checkpoint(machines, mlflow_http, tmp_path, capfd):
    machines.ensure_worker()
    steps, every = 140, 20
    argv = _argv(
        tmp_path,
        f"""
name: worker_kill
grid: {{priors.point_size: [0.04]}}
failure: {{max_retries: 1}}
profiles:
  smoke: {{budget: {{steps: {steps}, eval_every: {every}}}, resources: {{workers_per_trial: 1, cpus_per_worker: 0.99}}}}
""",
        mlflow_http,
    )
    train = tmp_path / "results" / "worker_kill" / "smoke" / "train"

    def checkpointed() -> bool:
        return any(_train_checkpoints(t) >= 3 for t in train.glob("trial_*"))

    def kill_worker() -> None:
        alive = [a for a in ray._private.state.actors().values()
                 if a["ActorClassName"] == "RayTrainWorker" and a["State"] == "ALIVE"]
        assert len(alive) == 1, alive
        os.kill(alive[0]["Pid"], signal.SIGKILL)

    code, injected, wall = _sweep_with_fault(argv, checkpointed, kill_worker)
    out = capfd.readouterr().out
    assert injected, f"the sweep ended before the trial checkpointed three times:\n{out[-3000:]}"
    assert code == 0, out[-3000:]
    print(f"\nkilled Train worker: {wall:.1f} s")

    label = "point_size=0.04 · seed 0"
    assert out.count(f"[{label}] resuming from") == 1, out[-3000:]
    after = _steps_after_resume(out, label)
    _assert_continued(after, every, steps)
    # Ray Train restarted the worker inside the same Tune trial: one trial, never failed.
    assert "✗ failed" not in out and "(1/1 trials done)" in out
    _assert_each_trial_once(mlflow_http, "worker_kill", trials=1, steps=steps)
    # Of the trial's 7 checkpoints Train keeps the newest two, named in its snapshot. A third folder may
    # be the one the killed worker was writing: uploaded, never registered, so never pruned.
    (run_dir,) = train.glob("trial_*")
    snapshot = json.loads((run_dir / "checkpoint_manager_snapshot.json").read_text())
    named = [r["checkpoint_dir_name"] for r in snapshot["checkpoint_results"]]
    folders = sorted(p.name for p in run_dir.glob("checkpoint_*") if p.is_dir())
    assert len(named) == 2 and set(named) <= set(folders) and sorted(named) == folders[-2:], (named, folders)
    assert len(folders) <= 3, folders


def test_killed_driver_after_one_finished_trial_resumes_the_rest(machines, mlflow_http, tmp_path, capfd):
    machines.ensure_worker()
    steps, every = 120, 30
    storage = str(tmp_path / "store")  # a URI's kill and resume: test_boundaries.py (S3)
    argv = _argv(tmp_path, f"""
name: driver_kill
grid: {{priors.point_size: [0.01, 0.02, 0.04]}}
failure: {{max_retries: 1}}
profiles: {{smoke: {{budget: {{steps: {steps}, eval_every: {every}}}}}}}
""", mlflow_http, storage)
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}  # the ray#59110 workaround, for the driver process
    log = tmp_path / "driver.log"
    with log.open("w") as fh:
        driver = subprocess.Popen(
            [sys.executable, str(ROOT / "sweeps" / "run.py"), *argv, "--address", machines.cluster.address],
            cwd=tmp_path,
            env=env,
            stdout=fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    folder = tmp_path / "store" / "driver_kill" / "smoke"
    finished_at: dict[str, float] = {}  # child run name → when the test first saw it FINISHED
    interrupted: set[str] = set()
    try:
        deadline = time.monotonic() + 150
        while time.monotonic() < deadline and driver.poll() is None:
            children = _children(mlflow_http, "driver_kill") if (folder / "sweep.json").exists() else []
            now = time.monotonic()
            for c in children:
                if c.info.status == "FINISHED":
                    finished_at.setdefault(c.info.run_name, now)
            # Unfinished trials that have checkpointed twice (the first is surely in Tune's snapshot by now).
            interrupted = {c.info.run_name for c in children if c.info.run_name not in finished_at
                           and _tune_checkpoints(folder / c.data.tags["tune_trial_dir"].rsplit("/", 1)[1]) >= 2}
            # Kill 3 s after a trial finished (Tune's snapshot of the sweep is up to ~1 s old: a trial that
            # finished within it is resumed from its last checkpoint instead), once another is mid-way.
            if finished_at and now - min(finished_at.values()) > 3 and interrupted:
                break
            time.sleep(0.2)
        assert driver.poll() is None, log.read_text()[-3000:]
        os.kill(driver.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        driver.wait()
    finally:
        _stop(driver, None)
    # Joined by address, the runner sizes nothing from the nodes up: all 3 trials are let in (2 run).
    assert "cluster (at most): 2 CPUs, 0 GPUs → up to 3 concurrent trials" in log.read_text()
    settled = {name for name, t in finished_at.items() if killed_at - t > 2}
    assert settled and interrupted and len(finished_at) < 3, (finished_at, interrupted)
    client = MlflowClient(mlflow_http)
    before = {
        c.info.run_name: c.data.metrics["eval/f1"]
        for c in _children(mlflow_http, "driver_kill")
        if c.info.run_name in settled
    }
    capfd.readouterr()

    assert run.main([*argv, "--resume"]) == 0  # in this process, already connected: joins the same cluster
    out = capfd.readouterr().out
    for label in before:
        assert f"▶ started [{label}]" not in out  # finished trials are not re-run
    for label in interrupted:  # the trial cut short goes on from its checkpoint
        _assert_continued(_steps_after_resume(out, label), every, steps)
    assert "(3/3 trials done)" in out
    children = _assert_each_trial_once(mlflow_http, "driver_kill", trials=3, steps=steps)
    # No finished result lost: each trial finished before the kill keeps its numbers, in MLflow and the table.
    assert {c.info.run_name: c.data.metrics["eval/f1"] for c in children if c.info.run_name in before} == before
    rows = {r["cell"]: r for r in csv.DictReader(io.StringIO((folder / "results.csv").read_text()))}
    assert all(rows[f"point_size={size}"]["ok"] == "1" for size in ("0.01", "0.02", "0.04")), rows
    for label, f1 in before.items():
        # MLflow holds the score the trial reported, unrounded; results.csv the same float (one seed: its mean).
        assert float(rows[label.removesuffix(" · seed 0")]["eval/f1 mean"]) == f1
    # The parent run holds the table.
    assert json.loads((folder / "sweep.json").read_text())["tracking_uri"] == mlflow_http
    assert (folder / "plan.json").is_file() and (folder / "results.md").is_file()
    parent = json.loads((folder / "sweep.json").read_text())["parent_run_id"]
    assert {"results.md", "results.csv"} <= {a.path for a in client.list_artifacts(parent)}
    assert f"results: {storage}/driver_kill/smoke/results.md" in out
    assert f"MLflow: open {mlflow_http}/#/experiments/" in out


def test_an_input_the_estimate_cannot_read_fails_in_one_line_and_leaves_no_sweep(
    machines, mlflow_http, tmp_path, capfd
):
    meshes = tmp_path / "meshes" / "chair"
    meshes.mkdir(parents=True)
    for i in range(4):
        (meshes / f"m{i}.obj").write_text("not a mesh")
    argv = [
        *_argv(
            tmp_path,
            f"name: unreadable\ngrid: {{priors.point_size: [0.04]}}\n"
            f"base: {{data.kind: meshes, data.root: {tmp_path / 'meshes'}, data.categories: [chair]}}\n",
            mlflow_http,
        ),
        "--address",
        machines.cluster.address,
    ]
    for _ in range(2):  # the same command again is refused for the input, not as "already holds a sweep"
        capfd.readouterr()
        assert run.main(argv) == 2
        err = capfd.readouterr().err
        errors = [line for line in err.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and "holds no triangles" in errors[0] and "Traceback" not in err, err
        assert not (tmp_path / "results" / "unreadable" / "smoke").exists()
    parents = [r for r in MlflowClient(mlflow_http).search_runs(
        [MlflowClient(mlflow_http).get_experiment_by_name("unreadable").experiment_id])]
    assert [r.info.status for r in parents] == ["FAILED", "FAILED"]
