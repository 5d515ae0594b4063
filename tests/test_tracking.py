"""MLflow adapter on a real SQLite store: absolute URIs, one child per trial, resume without duplicates."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import mlflow.artifacts
import torch
import yaml
from mlflow import MlflowClient

from cdm.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from cdm.config import load_config
from cdm.provenance import installed_packages, machine_record
from sweeps.execute.logged_runs import find_trial_run, last_eval_files
from sweeps.execute.tracking import SweepRun, resolve_tracking_uri, ui_command, ui_link
from sweeps.execute.trial_tracking import PACKAGES_FILE, TrialRun, learning_curve_png


def test_tracking_uri_is_absolute_and_overridable(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert resolve_tracking_uri(None, tmp_path) == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///sub/x.db")
    assert resolve_tracking_uri(None, tmp_path) == f"sqlite:///{tmp_path.resolve()}/sub/x.db"
    assert resolve_tracking_uri("http://10.0.0.5:5000", tmp_path) == "http://10.0.0.5:5000"
    assert resolve_tracking_uri("sqlite:////abs/m.db", tmp_path) == "sqlite:////abs/m.db"
    assert (
        ui_command("sqlite:////abs/m.db")
        == "mlflow ui --backend-store-uri sqlite:////abs/m.db --host 127.0.0.1 --port 5000"
    )


def test_child_runs_resume_without_duplicates_and_close_with_a_verdict(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={"profile": "smoke"}, params={"trials": 2})
    assert pickle.loads(pickle.dumps(sweep)).run_id == sweep.run_id  # Tune pickles it with its callbacks
    cfg = load_config(None, {"priors.point_size": 0.02, "train.steps": 10})  # evaluated at step 10: the last
    first = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "point_size=0.02 · seed 0", {"seed": "0"}, cfg)
    panel = tmp_path / "obj.png"
    panel.write_bytes(b"\x89PNG")
    for step in (5, 10):
        first.on_step(step, {"train/loss": 1.0 / step})
    first.on_eval(10, {"eval/cd": 50.0, "eval/f1": 0.3}, [panel])

    again = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "point_size=0.02 · seed 0", {"seed": "0"}, cfg)
    assert again.run_id == first.run_id and again.logged_until == {"train": 10, "eval": 10}
    for step in (5, 10, 15):  # a resumed fit repeats the steps after its last checkpoint
        again.on_step(step, {"train/loss": 2.0 / step})
    again.on_eval(10, {"eval/cd": 99.0}, [panel])

    client = MlflowClient(uri)
    history = [(m.step, m.value) for m in client.get_metric_history(first.run_id, "train/loss")]
    assert sorted(history) == [(5, 0.2), (10, 0.1), (15, 0.1333)]  # 2/15 at 4 significant digits
    assert [m.value for m in client.get_metric_history(first.run_id, "eval/cd")] == [50.0]
    run = client.get_run(first.run_id)
    # Every config field but the trial's own folder (different in every trial by construction).
    assert run.data.params["priors.point_size"] == "0.02" and set(run.data.params) == set(cfg.flat()) - {
        "train.out_dir"
    }
    assert run.data.tags["mlflow.parentRunId"] == sweep.run_id
    assert {a.path for a in client.list_artifacts(first.run_id)} == {"config.yaml", "eval", "curves"}
    assert last_eval_files(client, first.run_id) == ["eval/step_0000010/panels/obj.png"]  # panels apart from clouds

    curve = learning_curve_png(client, first.run_id, tmp_path)
    assert curve.read_bytes()[:4] == b"\x89PNG" and curve.stat().st_size > 2000

    sweep.close_trial("t0", "point_size=0.02 · seed 0", "FAILED", error="TrainingDiverged: loss became nan",
                      checkpoint="s3://bucket/sweeps/exp/smoke/trial_t0/checkpoint_000001")
    sweep.close_trial("t1", "point_size=0.04 · seed 0", "FAILED", error="died before training", checkpoint=None)
    t1 = find_trial_run(client, sweep.experiment_id, sweep.run_id, "t1")
    assert client.get_run(first.run_id).info.status == "FAILED" and client.get_run(t1).info.status == "FAILED"
    assert client.get_run(first.run_id).data.tags["error"] == "TrainingDiverged: loss became nan"
    assert client.get_run(first.run_id).data.tags["checkpoint"] == "s3://bucket/sweeps/exp/smoke/trial_t0/checkpoint_000001"
    assert "checkpoint" not in client.get_run(t1).data.tags  # it died before its first checkpoint
    children = client.search_runs([sweep.experiment_id], f"tags.mlflow.parentRunId = '{sweep.run_id}'")
    assert sorted(r.info.run_name for r in children) == ["point_size=0.02 · seed 0", "point_size=0.04 · seed 0"]


def test_final_and_parent_metrics_are_logged_at_the_tables_precision(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    cfg = load_config(None, {})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, cfg)
    table, cloud = tmp_path / "objects.csv", tmp_path / "o1.ply"
    table.write_text("object_id,category,eval_set,cd,f1\no1,chair,e1,60.942297,0.42000000000000004\n")
    cloud.write_text("ply\nend_header\n")
    for step in (5, 10):
        trial.on_step(step, {"train/loss": 3.0 / step, "train/loss_diffusion": 1.0 / step, "train/steps_per_s": 2.0,
                             "train/lr": 1.234567e-4})
    trial.on_eval(10, {"eval/cd": 60.942297, "eval/f1": 0.42000000000000004}, [table, cloud])
    sweep.close_trial("t0", "a · seed 0", "FINISHED")
    sweep.log_results({"e1": {"baseline/sphere/cd": 150.0049}}, "a")
    client = MlflowClient(uri)
    final = client.get_run(trial.run_id).data.metrics
    assert (final["final/cd"], final["final/f1"]) == (60.94, 0.42) and final["eval/cd"] == 60.94
    # Loop timings sit under MLflow's "System metrics", apart from the model charts.
    assert final["system/steps_per_s"] == 2.0 and "train/steps_per_s" not in final
    assert final["train/lr"] == 1.235e-4  # 4 significant digits: a small learning rate keeps its value
    parent = client.get_run(sweep.run_id).data.metrics
    assert parent == {"baseline/sphere/cd": 150.0}
    assert sorted(last_eval_files(client, trial.run_id)) == [
        "eval/step_0000010/clouds/o1.ply",
        "eval/step_0000010/objects.csv",
    ]
    assert "curves" not in {a.path for a in client.list_artifacts(trial.run_id)}  # drawn at the last evaluation only
    curve = learning_curve_png(client, trial.run_id, tmp_path)  # one evaluation: the loss terms only
    assert curve.stat().st_size > 2000


def test_the_experiment_is_a_model_training_one_and_every_link_opens_that_workflow(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    client = MlflowClient(uri)
    old = client.create_experiment("older")  # made before the tag existed, e.g. by an earlier sweep
    client.create_experiment("other")
    sweep = SweepRun.start(uri, "older", "older · smoke", tags={}, params={})
    assert (
        sweep.experiment_id == old
        and client.get_experiment(old).tags["mlflow.experimentKind"] == "custom_model_development"
    )
    client.delete_experiment_tag(old, "mlflow.experimentKind")
    SweepRun.reopen(uri, sweep.run_id)  # --resume tags it again
    assert client.get_experiment(old).tags["mlflow.experimentKind"] == "custom_model_development"
    new = SweepRun.start(uri, "new", "new · smoke", tags={}, params={}).experiment_id
    assert client.get_experiment(new).tags["mlflow.experimentKind"] == "custom_model_development"
    assert "mlflow.experimentKind" not in client.get_experiment_by_name("other").tags  # only the sweep's own
    assert ui_link("#/experiments/1/runs/abc") == "#/experiments/1/runs/abc?workflowType=machine_learning"
    assert (
        ui_link("#/experiments/1/runs?viewStateShareKey=k")
        == "#/experiments/1/runs?viewStateShareKey=k&workflowType=machine_learning"
    )


def test_a_child_run_keeps_its_last_checkpoints_weights_for_inference_as_model_artifacts(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    cfg = load_config(None, {"train.steps": 20, "train.out_dir": str(tmp_path / "scratch")})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, cfg)
    trial.on_start({"git_commit": "abc", "config_hash": "0123"})
    weights = {10: torch.full((3, 2), 1.0), 20: torch.full((3, 2), 2.0)}
    for step, w in weights.items():  # the second evaluation's weights replace the first's
        full = Checkpoint(config=cfg.to_dict(), step=step, voxel_backend="dense", model={"layer.weight": w},
                          ema={"layer.weight": w / 2}, optimizer={"state": {0: {"exp_avg": torch.ones(3, 2)}}},
                          scheduler={"last_epoch": step}, generator=torch.zeros(5, dtype=torch.uint8))
        trial.on_checkpoint(step, save_checkpoint(full, tmp_path / f"step_{step}").parent)

    client = MlflowClient(uri)
    run = client.get_run(trial.run_id)
    assert run.data.tags["model"] == f"runs:/{trial.run_id}/model"
    assert sorted(a.path for a in client.list_artifacts(trial.run_id, "model")) == [
        "model/checkpoint.json", "model/config.yaml", "model/ema.safetensors", "model/model.safetensors",
        "model/record.json"]
    folder = Path(mlflow.artifacts.download_artifacts(run.data.tags["model"], dst_path=str(tmp_path / "down"),
                                                      tracking_uri=uri))
    model = load_checkpoint(folder)  # safetensors and JSON
    assert model.step == 20 and torch.equal(model.model["layer.weight"], weights[20])
    assert torch.equal(model.weights["layer.weight"], weights[20] / 2)  # EMA: what evaluation samples with
    assert (model.optimizer, model.scheduler, model.generator) == (None, None, None)
    assert "out_dir" not in model.config["train"]  # the scratch folder is no part of the record
    assert json.loads((folder / "record.json").read_text()) == {"step": 20, "git_commit": "abc", "config_hash": "0123"}
    logged = yaml.safe_load((folder / "config.yaml").read_text())
    assert "out_dir" not in logged["train"] and logged["train"]["steps"] == 20
    assert (tmp_path / "step_20" / "training.safetensors").is_file() and not (folder / "training.safetensors").exists()


def test_a_child_run_is_tagged_with_its_machine_and_holds_its_package_list(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, load_config(None))
    machine = machine_record()
    trial.on_start({"config_hash": "0" * 16, **machine})
    client = MlflowClient(uri)
    tags = client.get_run(trial.run_id).data.tags
    assert {k: tags[f"repro.{k}"] for k in machine} == machine and tags["repro.cpu_capability"]
    listed = Path(client.download_artifacts(trial.run_id, PACKAGES_FILE, str(tmp_path))).read_text().splitlines()
    assert listed == installed_packages() and any(line.startswith("torch==") for line in listed)
