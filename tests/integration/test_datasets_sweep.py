"""A smoke sweep on each real data-set layout (fixture trees), with ``data.kind`` switched by ``--set``.

Real local Ray cluster and MLflow store, smoke profile, one cell: the loaders must work inside Ray
trials exactly as in tests/test_data_*.py.
"""

from __future__ import annotations

import time

import pytest
from mlflow import MlflowClient

from sweeps import run
from tests.datasets_fixtures import make_co3d, make_shapenet

pytestmark = [pytest.mark.ray, pytest.mark.slow]


def _smoke(tmp_path, kind: str, root, *sets: str) -> float:
    spec = tmp_path / "spec.yaml"
    spec.write_text(f"name: {kind}\ngrid: {{priors.point_size: [0.04]}}\n")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    argv = [str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri,
            "--set", f"data.kind={kind}", "--set", f"data.root={root}", *[a for s in sets for a in ("--set", s)]]
    start = time.perf_counter()
    assert run.main(argv) == 0
    wall = time.perf_counter() - start
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name(kind).experiment_id])
    child = next(r for r in runs if "mlflow.parentRunId" in r.data.tags)
    assert child.info.status == "FINISHED"
    assert child.data.params["data.kind"] == kind and child.data.params["data.root"] == str(root)
    assert 0.0 <= child.data.metrics["eval/f1"] <= 1.0 and child.data.metrics["eval/cd"] > 0
    return wall


def test_smoke_sweep_on_shapenet_r2n2(cluster, tmp_path):
    tree = make_shapenet(tmp_path / "shapenet", per_split={"train": 2, "val": 1})
    wall = _smoke(tmp_path, "shapenet_r2n2", tree.root, "priors.render_kind=planar")
    print(f"\nshapenet_r2n2 smoke sweep: {wall:.1f} s")


def test_smoke_sweep_on_co3d(cluster, tmp_path):
    tree = make_co3d(tmp_path / "co3d")
    wall = _smoke(tmp_path, "co3d", tree.root, "data.categories=[teddybear,hydrant]", "priors.prior_2d=depth")
    print(f"\nco3d smoke sweep: {wall:.1f} s")
