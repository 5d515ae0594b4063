"""Smoke runs of the two sweeps that read external inputs, on inputs written here.

``sweeps/global_features.yaml`` (Table 7) reads ``$CDM_INPUTS/openclip/{text,image,depth}.npz`` and
``sweeps/conditions.yaml`` (Table 8) ``$CDM_INPUTS/controlnet``; both run every row of their table
on the smoke profile with random embeddings and plain-colour "generated" images.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from mlflow import MlflowClient

from sweeps import run
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from tests.input_fixtures import object_ids, write_condition_images, write_embeddings
from tests.integration.local_ray import local_ray

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("inputs")
    cfg = expand(load_spec(ROOT / "sweeps" / "conditions.yaml"), "smoke").cells[0].config
    ids = object_ids(cfg)
    for seed, kind in enumerate(("text", "image", "depth")):
        write_embeddings(folder / "openclip" / f"{kind}.npz", ids, (16,), seed)
    write_condition_images(folder / "controlnet", ids, views=3, size=cfg.data.image_size)
    return folder


@pytest.fixture(scope="module")
def cluster(inputs):
    mp = pytest.MonkeyPatch()
    mp.setenv("CDM_INPUTS", str(inputs))  # before Ray starts: its workers inherit the environment
    with local_ray():
        yield
    mp.undo()


@pytest.mark.parametrize(("spec", "rows"), [("global_features", 6), ("conditions", 7)])
def test_smoke_sweep_runs_every_row(cluster, tmp_path, capsys, spec, rows):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    argv = [
        str(ROOT / "sweeps" / f"{spec}.yaml"),
        "--smoke",
        "--out",
        str(tmp_path / "results"),
        "--tracking-uri",
        uri,
    ]
    assert run.main(argv) == 0
    out = capsys.readouterr().out
    assert "MISSING" not in out and "external inputs:" in out
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(spec)
    children = [r for r in client.search_runs([exp.experiment_id]) if "mlflow.parentRunId" in r.data.tags]
    assert len(children) == rows and all(r.info.status == "FINISHED" for r in children)
    assert all("eval/f1" in r.data.metrics for r in children)
    table = (tmp_path / "results" / spec / "smoke" / "results.md").read_text()
    assert table.count("0.428") >= 1  # row 1, the PC² baseline, beside its paper number
