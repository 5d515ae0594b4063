"""A trial the driver closed just before it was killed is recognised on --resume from its own MLflow record
(real SQLite store): its metrics come back instead of a re-run, and its ``final/…`` metrics are logged once."""

from __future__ import annotations

from mlflow import MlflowClient

from cdm.config import load_config
from sweeps.execute.logged_runs import finished_trial_metrics
from sweeps.execute.tracking import SweepRun
from sweeps.execute.trial_tracking import TrialRun


def test_finished_trial_is_recognised_and_its_final_metrics_logged_once(tmp_path):
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
