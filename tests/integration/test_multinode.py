"""Sweeps on a real two-node Ray cluster (``ray.cluster_utils.Cluster``: two raylets of 1 CPU each on
this machine, head on 127.0.0.1), run by the sweep runner exactly as on a cluster (issue 5).

- Two concurrent smoke trials of 1 CPU each cannot share a node, so one lands on each; neither records a
  path that only its node can read (issue 53).
- One trial with ``workers_per_trial: 2`` (0.99 CPU each, so never both on one node) trains
  data-parallel over gloo; every rank checkpoints its own model, and rank 0's and rank 1's weights
  must be identical at every checkpoint although each rank drew different batches and noise
  (``cdm.train`` averages gradients over ranks before each step).

Where each actor ran is read from the GCS actor table (no dashboard needed).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import ray
import torch
from mlflow import MlflowClient

from cdm.checkpoint import CHECKPOINT_FILE, load_checkpoint
from sweeps import run
from sweeps.execute.trial import trial_scratch
from tests.integration.local_ray import TwoNodes, two_node_cluster

pytestmark = [pytest.mark.ray, pytest.mark.slow]


@pytest.fixture(scope="module")
def two_nodes() -> Iterator[TwoNodes]:
    """A head and a worker node, 1 CPU each; the driver is connected to the head."""
    with two_node_cluster() as cluster:
        yield cluster


def _actor_nodes(class_name: str) -> list[str]:
    """Node ids where actors of ``class_name`` ran, alive or dead, from the GCS actor table."""
    table = ray._private.state.actors()
    return [a["Address"]["NodeID"] for a in table.values() if a["ActorClassName"] == class_name]


def _sweep(tmp_path: Path, body: str) -> tuple[list[str], str]:
    spec = tmp_path / "spec.yaml"
    spec.write_text(body)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    return [str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri], uri


def _node_local(path: str, cluster: TwoNodes, sweep_dir: Path, trial_id: str) -> bool:
    """Whether ``path`` lies where only the node that wrote it can read it on a real cluster: a node's Ray
    temporary folder, or the trial's scratch folder."""
    scratch = trial_scratch(str(sweep_dir), trial_id)
    return any(Path(path).is_relative_to(p) for p in (cluster.temp_dir, scratch.parent))


def test_concurrent_trials_run_on_both_nodes_and_record_no_node_local_path(two_nodes, tmp_path):
    argv, uri = _sweep(tmp_path, "name: spread\ngrid: {priors.point_size: [0.02, 0.04]}\n")
    assert run.main(argv) == 0
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("spread").experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert sorted(c.info.status for c in children) == ["FINISHED", "FINISHED"]
    # Each trial records the node its actor ran on (read inside the trial, not from the actor table).
    placed = [c.data.tags["ray_node_id"] for c in children]
    assert set(placed) == set(two_nodes.nodes), placed
    # The trial on the worker node too: its checkpoint and folder are in the sweep's storage, its weights in
    # MLflow's artifact store, nothing in either node's temporary folders.
    sweep_dir = tmp_path / "results" / "spread" / "smoke"
    for child in children:
        tags, trial_id = child.data.tags, child.data.tags["trial_id"]
        paths = {k: v for k, v in tags.items() if v.startswith("/")}
        assert {"checkpoint", "tune_trial_dir"} <= set(paths)
        for key, path in paths.items():
            assert Path(path).is_relative_to(sweep_dir) and Path(path).exists(), f"{key} = {path}"
            assert not _node_local(path, two_nodes, sweep_dir, trial_id), f"{key} = {path} is node-local"
        assert Path(tags["checkpoint"], CHECKPOINT_FILE).is_file()
        models = client.search_logged_models([child.info.experiment_id])  # the weights: the run's MLflow model
        assert [m.name for m in models if m.source_run_id == child.info.run_id] == ["model"]


def test_two_worker_trial_spans_nodes_and_keeps_ranks_identical(two_nodes, tmp_path):
    before = len(_actor_nodes("RayTrainWorker"))
    argv, uri = _sweep(tmp_path, """
name: ddp
grid: {priors.point_size: [0.04]}
profiles: {smoke: {resources: {workers_per_trial: 2, cpus_per_worker: 0.99}}}
""")
    assert run.main(argv) == 0
    workers = _actor_nodes("RayTrainWorker")[before:]
    assert len(workers) == 2 and set(workers) == set(two_nodes.nodes), workers

    # Rank 0's checkpoints as Ray Train keeps them in the sweep's storage (none left in its scratch folder);
    # rank 1's in its own node's scratch folder (both nodes share this machine's disk).
    sweep_dir = tmp_path / "results" / "ddp" / "smoke"
    (trial_dir,) = sweep_dir.glob("trial_*")
    trial_id = trial_dir.name.removeprefix("trial_")
    rank0 = sorted(p for p in (sweep_dir / "train" / trial_dir.name).glob("checkpoint_*") if p.is_dir())
    scratch = trial_scratch(str(sweep_dir), trial_id)
    assert not list(scratch.glob("checkpoints/step_*"))
    rank1 = sorted((scratch / "rank_1" / "checkpoints").glob("step_*"))
    assert [p.name for p in rank1] == ["step_0000010", "step_0000020"] and len(rank0) == 2
    for a, b in zip(rank0, rank1):
        sa, sb = (vars(load_checkpoint(c)) for c in (a, b))
        assert sa["step"] == sb["step"]
        # Different data per rank (their generators are seeded by rank) ...
        assert not torch.equal(sa["generator"], sb["generator"])
        # ... yet the same weights: the gradients were all-reduced before every step.
        assert sa["model"].keys() == sb["model"].keys()
        for key in sa["model"]:
            assert torch.equal(sa["model"][key], sb["model"][key]), f"{a.name}: {key} differs between ranks"
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("ddp").experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(children) == 1 and children[0].info.status == "FINISHED"
    assert Path(children[0].data.tags["checkpoint"]) == rank0[-1]  # the Train run's newest, in storage
    # Only rank 0 logs: each step once.
    steps = [m.step for m in client.get_metric_history(children[0].info.run_id, "train/loss")]
    assert sorted(steps) == [5, 10, 15, 20]
