"""What a trial pays per checkpoint to log its weights: a plain ``model/`` folder (0.1.0) against an MLflow model.

A trial logs its inference weights at every checkpoint (``TrialRun.on_checkpoint``). 0.1.0 copied the folder into
the run's artifacts (``log_artifacts``); now :func:`sweeps.mlflow_model.log_model` writes an MLflow model (MLmodel,
the model's code, requirements) around the same folder and re-logs it into the run's one logged model. Both are
timed side by side on one SQLite store, on the inference checkpoint of the ``local`` profile's network
(sweeps/profiles.yaml; untrained weights: their values do not change the cost), after one untimed round each; the
first call of a process (MLflow's model modules imported) is timed apart.

    python benchmarks/model_logging.py [--repeats 10]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # `python benchmarks/model_logging.py`: the repository root on the path
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mlflow import MlflowClient

from benchmarks.common import paired
from cdm.checkpoint import Checkpoint, save_checkpoint
from cdm.config import load_config
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.model import CDMNetwork
from sweeps.plan.profiles import load_profiles

__all__ = ["logging_cost", "model_logging"]


def _checkpoint(folder: Path) -> Path:
    """The ``local`` profile's network saved as an inference checkpoint (weights and EMA) in ``folder``."""
    cfg = load_config(None, {**load_profiles()["local"].overrides, "train.device": "cpu"})
    network = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d], device="cpu")
    weights = network.state_dict()
    save_checkpoint(Checkpoint(cfg.to_dict(), 1, cfg.model.voxel_backend, weights, ema=weights,
                               encoder=network.encoder.record), folder)
    return folder


def logging_cost(repeats: int) -> dict[str, float]:
    """Seconds per log, old and new (medians), their ratio, the new one's first call, and the folder's MB."""
    from sweeps.mlflow_model import log_model

    with tempfile.TemporaryDirectory(prefix="cdm-bench-") as tmp:
        folder = _checkpoint(Path(tmp) / "checkpoint")
        client = MlflowClient(f"sqlite:///{tmp}/mlflow.db")
        experiment = client.create_experiment("bench", artifact_location=(Path(tmp) / "mlruns").as_uri())
        old_run, new_run = (client.create_run(experiment).info.run_id for _ in range(2))
        start = time.perf_counter()
        log_model(client, new_run, folder, {"step": 1})
        first = time.perf_counter() - start
        timing = paired(lambda: client.log_artifacts(old_run, str(folder), "model"),
                        lambda: log_model(client, new_run, folder, {"step": 1}), repeats)
        size_mb = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20
    return {"folder_s": timing.a_s, "mlflow_model_s": timing.b_s, "ratio": timing.ratio, "first_call_s": first,
            "checkpoint_mb": size_mb}


def model_logging(quick: bool, out_dir: str) -> list[dict]:
    """The row of ``benchmarks/run.py``: 0.1.0's folder (a) against the MLflow model (b), per checkpoint."""
    cost = logging_cost(3 if quick else 10)
    return [{"benchmark": "model logging", "case": f"local profile, {cost['checkpoint_mb']:.1f} MB per checkpoint",
             "without_s": cost["folder_s"], "with_s": cost["mlflow_model_s"], "ratio": cost["ratio"],
             "target": "< 1 s per checkpoint"}]


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # as in a sweep (sweeps/store/tracking.py)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=10, help="timed rounds of each (default 10)")
    cost = logging_cost(p.parse_args(argv).repeats)
    print(f"inference checkpoint of the local profile: {cost['checkpoint_mb']:.2f} MB")
    print(f"plain folder (0.1.0)   {cost['folder_s'] * 1000:8.1f} ms per checkpoint")
    print(f"MLflow model           {cost['mlflow_model_s'] * 1000:8.1f} ms per checkpoint "
          f"({cost['ratio']:.2f}× the folder's); first call of a process {cost['first_call_s']:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
