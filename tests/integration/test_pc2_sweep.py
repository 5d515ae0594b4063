"""A sweep cell scoring PC²'s released weights (``model.init_from`` + ``eval.only``) on real Ray and MLflow:
the trial evaluates at step 0, finishes as a complete trial, and its file is read where it runs."""

from __future__ import annotations

import pytest
from mlflow import MlflowClient

from sweeps import run
from tests.integration.local_ray import local_ray
from tests.pc2_files import write_pc2_checkpoint

pytestmark = [pytest.mark.ray, pytest.mark.slow]

SPEC = """\
name: pc2_released
description: PC²'s released weights scored as a cell, without training
cells:
  - label: PC² (released weights)
    set: {priors.prior_2d: none, priors.prior_3d: false, eval.only: true,
          model.init_from: '$CDM_INPUTS/pc2/{category}/checkpoint-latest.pth', model.denoiser: pvcnn2,
          model.encoder: vit_s16, model.feature_dim: 384, model.width_multiplier: 0.25,
          model.voxel_resolution_multiplier: 0.25, model.time_embed_dim: 64, diffusion.prediction: eps,
          diffusion.sampler: ddpm, diffusion.ddpm_steps: 2, diffusion.clip_x0: null}
grid:
  data.categories: [[chair]]
seeds: [0]
metric: {name: eval/cd, mode: min}
"""


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    inputs = tmp_path_factory.mktemp("inputs")
    (inputs / "pc2" / "chair").mkdir(parents=True)
    write_pc2_checkpoint(inputs / "pc2" / "chair" / "checkpoint-latest.pth", width=0.25)
    mp = pytest.MonkeyPatch()
    mp.setenv("CDM_INPUTS", str(inputs))  # before Ray starts: its workers inherit the environment
    with local_ray():
        yield inputs
    mp.undo()


def test_a_cell_scores_pc2s_released_weights_at_step_0_as_a_finished_trial(cluster, tmp_path, capsys):
    spec = tmp_path / "pc2_released.yaml"
    spec.write_text(SPEC)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    assert run.main([str(spec), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri]) == 0
    out = capsys.readouterr().out
    assert f"model.init_from={cluster}/pc2/chair/checkpoint-latest.pth (ok)" in out
    assert "✓ finished [PC² (released weights) · categories=chair · seed 0] at step 0: eval/cd" in out
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("pc2_released")
    (child,) = [r for r in client.search_runs([exp.experiment_id]) if "mlflow.parentRunId" in r.data.tags]
    assert child.info.status == "FINISHED" and child.data.params["eval.only"] == "True"
    assert [m.step for m in client.get_metric_history(child.info.run_id, "eval/cd")] == [0]
    metrics = child.data.metrics
    assert metrics["final/cd"] == metrics["eval/cd"] > 0 and "train/loss" not in metrics  # scored, never trained
    table = (tmp_path / "results" / "pc2_released" / "smoke" / "results.md").read_text()
    assert "stopped" not in table
