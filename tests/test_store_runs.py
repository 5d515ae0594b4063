"""The store's record on a real SQLite MLflow store: absolute URIs, one child per trial, resume without duplicates."""

from __future__ import annotations

import json
import pickle
import time
from pathlib import Path

import mlflow.artifacts
import torch
from mlflow import MlflowClient
from mlflow.models import Model

from cdm.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from cdm.config import F1_THRESHOLD, load_config
from cdm.metric_names import CD
from cdm.provenance import code_version, installed_packages, machine_record
from sweeps.execute.trial import learning_curve
from sweeps.mlflow_model import model_checkpoint
from sweeps.store.read import find_trial_run, finished_trial_metrics, last_eval_files, metric_histories
from sweeps.store.sweep_run import SweepRun
from sweeps.store.tracking import resolve_tracking_uri, ui_command, ui_link
from sweeps.store.trial_run import CURVE_KEYS, PACKAGES_FILE, TrialRun, system_metrics_monitor


def _curve(client, run_id: str, folder: Path) -> Path | None:
    """The learning curve a trial draws at its last evaluation, from its run's history."""
    history = metric_histories(client, run_id, (*CURVE_KEYS, CD.key))
    return learning_curve(history, folder, CD.key, "", F1_THRESHOLD)


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
    first = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "point_size=0.02 · seed 0", {"seed": "0"}, cfg,
                     curve=learning_curve)
    panel = tmp_path / "obj.png"
    panel.write_bytes(b"\x89PNG")
    for step in (5, 10):
        first.on_step(step, {"train/loss": 1.0 / step})
    first.on_eval(10, {"eval/cd": 50.0, "eval/f1": 0.3}, [panel])

    again = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "point_size=0.02 · seed 0", {"seed": "0"}, cfg,
                     curve=learning_curve)
    assert again.run_id == first.run_id and again.logged_until == {"train": 10, "eval": 10}
    for step in (5, 10, 15):  # a resumed fit repeats the steps after its last checkpoint
        again.on_step(step, {"train/loss": 2.0 / step})
    again.on_eval(10, {"eval/cd": 99.0}, [panel])

    client = MlflowClient(uri)
    history = [(m.step, m.value) for m in client.get_metric_history(first.run_id, "train/loss")]
    assert sorted(history) == [(5, 0.2), (10, 0.1), (15, 2.0 / 15)]  # at full precision
    assert [m.value for m in client.get_metric_history(first.run_id, "eval/cd")] == [50.0]
    run = client.get_run(first.run_id)
    # Every config field but the trial's own folder (different in every trial by construction).
    assert run.data.params["priors.point_size"] == "0.02" and set(run.data.params) == set(cfg.flat()) - {
        "train.out_dir"
    }
    assert run.data.tags["mlflow.parentRunId"] == sweep.run_id
    assert {a.path for a in client.list_artifacts(first.run_id)} == {"config.yaml", "eval", "curves"}
    assert last_eval_files(client, first.run_id) == ["eval/step_0000010/panels/obj.png"]  # panels apart from clouds

    curve = _curve(client, first.run_id, tmp_path)
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


def test_every_metric_is_logged_at_full_precision_and_per_category_scores_are_metrics(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL", "0.2")  # MLflow's own override of our 10 s
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    cfg = load_config(None, {"train.steps": 10})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {"repro.git_commit": "f" * 40}, cfg)
    trial.on_start({"config_hash": "0" * 16})
    table, cloud = tmp_path / "objects.csv", tmp_path / "o1.ply"
    table.write_text("object_id,category,eval_set,cd,f1\no1,chair,e1,60.942297,0.42000000000000004\n"
                     "o2,lamp,e1,61.5,0.5\n")
    cloud.write_text("ply\nend_header\n")
    steps = {5: {"train/loss": 3.0 / 5, "train/steps_per_s": 2.0 / 3.0, "train/lr": 1.234567e-4},
             10: {"train/loss": 2.0 / 15, "train/steps_per_s": 0.123456789, "train/lr": 1.234567e-4}}
    for step, metrics in steps.items():
        trial.on_step(step, metrics)
    scores = {"eval/cd": 60.942297123456, "eval/f1": 0.42000000000000004, "eval/f1/chair": 0.6123456789012345,
              "eval/f1/lamp": 0.5999999999999999, "eval/cd/chair": 60.942297123456, "eval/cd/lamp": 61.5,
              "baseline/sphere/cd": 150.0049}
    client = MlflowClient(uri)
    for _ in range(100):  # the monitor's first sample, taken in the background, before the trial ends
        if "system/cpu_utilization_percentage" in client.get_run(trial.run_id).data.metrics:
            break
        time.sleep(0.1)
    trial.on_eval(10, scores, [table, cloud])
    assert trial.monitor is None  # stopped at the last evaluation
    sweep.close_trial("t0", "a · seed 0", "FINISHED", last=scores)
    sweep.log_results({"e1": {"baseline/sphere/cd": 150.00491234, "baseline/sphere/cd/chair": 1 / 3}}, "a")
    run = client.get_run(trial.run_id)
    final = run.data.metrics
    # The very floats the trainer reported: MLflow holds them unrounded, the loop's timings under their own names.
    for step, metrics in steps.items():
        for key, value in metrics.items():
            assert [m.value for m in client.get_metric_history(trial.run_id, key) if m.step == step] == [value]
    assert final["eval/cd"] == final["final/cd"] == 60.942297123456 and final["final/f1"] == 0.42000000000000004
    assert final["final/f1/chair"] == 0.6123456789012345 and final["final/f1/lamp"] == 0.5999999999999999
    assert not [k for k in run.data.params if k.startswith("final/")]
    # MLflow's system-metrics monitor (psutil) fills system/, sampled in the background and flushed at the end.
    assert final["system/cpu_utilization_percentage"] >= 0 and final["system/system_memory_usage_megabytes"] > 0
    assert not [k for k in final if k.startswith("system/") and "steps" in k]
    # A per-category score is a metric MLflow filters and sorts on.
    for query in ('metrics."final/f1/chair" > 0.6', "metrics.`final/f1/lamp` < 0.6"):
        assert [r.info.run_id for r in client.search_runs([sweep.experiment_id], query)] == [trial.run_id]
    assert client.search_runs([sweep.experiment_id], 'metrics."final/f1/lamp" > 0.6') == []
    assert client.get_run(sweep.run_id).data.metrics == {"baseline/sphere/cd": 150.00491234,
                                                         "baseline/sphere/cd/chair": 1 / 3}
    # MLflow's own source tags beside the reproducibility record, on the child and the parent.
    tags = run.data.tags
    assert (tags["mlflow.source.git.commit"], tags["repro.git_commit"]) == ("f" * 40, "f" * 40)
    assert (tags["mlflow.source.name"], tags["mlflow.source.type"]) == ("sweeps/run.py", "LOCAL")
    parent_tags = client.get_run(sweep.run_id).data.tags
    assert parent_tags["mlflow.source.git.commit"] == code_version()["git_commit"]
    # The evaluation set as the run's dataset input: its fingerprint the digest, its objects counted per category.
    (used,) = run.inputs.dataset_inputs
    assert (used.dataset.name, used.dataset.digest, used.dataset.source_type) == ("procedural quick eval", "e1", "code")
    assert json.loads(used.dataset.profile) == {"num_objects": 2, "categories": {"chair": 1, "lamp": 1}}
    assert [(t.key, t.value) for t in used.tags] == [("mlflow.data.context", "eval")] and tags["eval_set"] == "e1"
    assert sorted(last_eval_files(client, trial.run_id)) == [
        "eval/step_0000010/clouds/o1.ply",
        "eval/step_0000010/objects.csv",
    ]
    curve = _curve(client, trial.run_id, tmp_path)  # one evaluation: the loss terms only
    assert curve.stat().st_size > 2000


def test_system_metrics_are_off_where_mlflows_switch_says_so(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING", "false")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, load_config(None))
    trial.on_start({"config_hash": "0" * 16})
    assert trial.monitor is None and system_metrics_monitor(uri, trial.run_id, resumed=False) is None


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


def test_a_child_run_keeps_its_last_checkpoints_weights_for_inference_as_its_mlflow_model(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    # MLflow finds a run's logged model through the process's tracking URI, whatever download_artifacts is given.
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    cfg = load_config(None, {"train.steps": 20, "train.out_dir": str(tmp_path / "scratch")})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "a · seed 0", {}, cfg)
    trial.on_start({"git_commit": "abc", "config_hash": "0123"})
    weights = {10: torch.full((3, 2), 1.0), 20: torch.full((3, 2), 2.0)}
    for step, w in weights.items():  # the second evaluation's weights replace the first's
        full = Checkpoint(config=cfg.to_dict(), step=step, voxel_backend="dense", model={"layer.weight": w},
                          ema={"layer.weight": w / 2}, optimizer={"state": {0: {"exp_avg": torch.ones(3, 2)}}},
                          scheduler={"last_epoch": step}, generator=torch.zeros(5, dtype=torch.uint8))
        save_checkpoint(full, tmp_path / f"step_{step}")
        trial.on_checkpoint(step, tmp_path / f"step_{step}")

    client = MlflowClient(uri)
    run = client.get_run(trial.run_id)
    assert run.data.tags["model"] == f"runs:/{trial.run_id}/model"
    models = client.search_logged_models([sweep.experiment_id])
    assert [(m.name, m.source_run_id) for m in models] == [("model", trial.run_id)]  # one model, replaced
    assert [o.model_id for o in run.outputs.model_outputs] == [models[0].model_id]
    folder = Path(mlflow.artifacts.download_artifacts(run.data.tags["model"], dst_path=str(tmp_path / "down")))
    info = Model.load(str(folder))
    assert info.metadata == {"step": 20, "git_commit": "abc", "config_hash": "0123"} and info.run_id == trial.run_id
    model = load_checkpoint(model_checkpoint(folder))  # safetensors and JSON
    assert model.step == 20 and torch.equal(model.model["layer.weight"], weights[20])
    assert torch.equal(model.weights["layer.weight"], weights[20] / 2)  # EMA: what evaluation samples with
    assert (model.optimizer, model.scheduler, model.generator) == (None, None, None)
    assert "out_dir" not in model.config["train"]  # the scratch folder is no part of the record
    checkpoint = model_checkpoint(folder)
    assert sorted(p.name for p in checkpoint.iterdir()) == ["checkpoint.json", "ema.safetensors", "model.safetensors"]
    assert (tmp_path / "step_20" / "training.safetensors").is_file()  # the full checkpoint keeps the optimiser


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


def test_finished_trial_is_recognised_and_its_final_metrics_logged_once(tmp_path):
    # A trial the driver closed just before it was killed is recognised on --resume from its own MLflow record:
    # its metrics come back instead of a re-run, and its ``final/…`` metrics are logged once.
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, "exp", "exp · smoke", tags={}, params={})
    trial = TrialRun(uri, sweep.experiment_id, sweep.run_id, "t0", "cell · seed 0", {}, load_config(None))
    for step, cd, f1 in ((10, 60.0, 0.2), (20, 40.0, 0.35)):
        trial.on_step(step, {"train/loss": 1.0 / step})
        trial.on_eval(step, {"eval/cd": cd, "eval/f1": f1}, [])
    assert finished_trial_metrics(uri, sweep.experiment_id, sweep.run_id, "t0") is None  # still RUNNING
    assert finished_trial_metrics(uri, sweep.experiment_id, sweep.run_id, "t1") is None  # no run at all

    sweep.close_trial(
        "t0", "cell · seed 0", "FINISHED", last={"eval/cd": 40.0, "eval/f1": 0.35, "eval/f1/chair": 0.3456}
    )
    done = finished_trial_metrics(uri, sweep.experiment_id, sweep.run_id, "t0")
    # The per-category score the child logged only as final/f1/chair comes back under its reported name.
    assert done == {"train/loss": 0.05, "eval/cd": 40.0, "eval/f1": 0.35, "eval/f1/chair": 0.3456, "step": 20}

    sweep.close_trial("t0", "cell · seed 0", "FINISHED")  # Tune closes it again after the resume
    client = MlflowClient(uri)
    history = client.get_metric_history(trial.run_id, "final/f1")
    assert [(m.step, m.value) for m in history] == [(20, 0.35)]
