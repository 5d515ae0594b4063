"""A sweep trial's weights as an MLflow model (``python_function``), defined from code: this file is the model.

MLflow's models-from-code: :func:`log_model` gives MLflow the path of this file, which MLflow copies into the
model beside the trial's inference checkpoint (the artifact ``checkpoint``, written by
:func:`cdm.checkpoint.save_checkpoint`); ``mlflow.pyfunc.load_model`` runs that copy, whose last line sets
:class:`PointCloudModel`, and :meth:`PointCloudModel.load_context` reads the weights through
:func:`cdm.checkpoint.load_network`. Nothing is pickled: loading needs the ``cdm-lab`` package, no code of the run.

The model samples as ``cdm-lab reconstruct`` does, from the same preparation (:mod:`cdm.single_image`):

- input ``image``: one ``(H, W, 3)`` uint8 RGB image, or ``(H, W, 4)`` RGBA whose alpha marks the object
  (the mask; without alpha the object is every pixel unlike the corners' colour). One image per call: the
  signature fixes the number of axes, so a batch is a loop over ``predict``.
- params ``camera``: ``[elev°, azim°, dist, focal]`` of the input camera (:class:`cdm.single_image.LookAt`,
  default ``[20, 0, 3.5, 2]``); ``seed``: the sampler's noise (default 0), the same seed giving the same cloud.
- output: ``(N, 3)`` float32 points (x, y, z) in the data set's world frame, ``N = data.num_points``.
"""

from __future__ import annotations

import tempfile
import warnings
from importlib.metadata import version
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import torch
from mlflow.models import ModelSignature, set_model
from mlflow.pyfunc import PythonModel
from mlflow.types import ParamSchema, ParamSpec, Schema, TensorSpec

from cdm.checkpoint import load_network
from cdm.evaluate import reconstruct
from cdm.io.yaml import read_mapping
from cdm.single_image import DEFAULT_VIEW, LookAt, image_batch, image_tensors

__all__ = ["CHECKPOINT_ARTIFACT", "MODEL_NAME", "PointCloudModel", "log_model", "logged_model", "model_checkpoint",
           "signature"]

MODEL_NAME = "model"
"""The model's name in its run: ``runs:/<run id>/model`` resolves to it."""

CHECKPOINT_ARTIFACT = "checkpoint"
"""The model's artifact holding the inference checkpoint folder (``cdm.checkpoint.save_checkpoint``'s files)."""


def signature() -> ModelSignature:
    """The model's input (``image``), output (points) and params (``camera``, ``seed``), as the module says."""
    return ModelSignature(
        inputs=Schema([TensorSpec(np.dtype(np.uint8), (-1, -1, -1), "image")]),
        outputs=Schema([TensorSpec(np.dtype(np.float32), (-1, 3), "points")]),
        params=ParamSchema([ParamSpec("camera", "double", [float(v) for v in DEFAULT_VIEW], (-1,)),
                            ParamSpec("seed", "long", 0)]),
    )


def _view(camera: Any) -> LookAt:
    """``camera`` (4 numbers) as a :class:`LookAt`, or one error naming the param."""
    try:
        values = np.asarray(camera, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        values = np.empty(0)
    if values.size != len(LookAt._fields) or not np.isfinite(values).all() or values[2] <= 0 or values[3] <= 0:
        raise ValueError(f"camera: {camera!r} is not [elev°, azim°, dist, focal] (4 finite numbers, dist and focal "
                         f"> 0); the default is {list(DEFAULT_VIEW)}")
    return LookAt(*values.tolist())


class PointCloudModel(PythonModel):
    """A trial's network, sampling one point cloud per image (the module says what goes in and out)."""

    # The logged signature checks the input; a type hint could not say "a dict of arrays or an array", and
    # without one MLflow warns at every import (its own ChatModel opts out the same way).
    _skip_type_hint_validation = True

    def load_context(self, context) -> None:
        # The device where it loads, not where it trained: a model trained on CUDA loads on a laptop.
        self.loaded = load_network(context.artifacts[CHECKPOINT_ARTIFACT], {"train.device": "auto"})

    def predict(self, context, model_input, params: dict[str, Any] | None = None) -> np.ndarray:
        """``model_input``: ``{"image": (H, W, 3|4) uint8}`` (or the array alone); returns ``(N, 3)`` float32."""
        cfg, network, diffusion, device = self.loaded
        params = params or {}
        pixels = model_input["image"] if isinstance(model_input, dict) else model_input
        image, mask = image_tensors(np.asarray(pixels), cfg.data.image_size, "image", "the input")
        batch = image_batch(image, mask, cfg, _view(params.get("camera", DEFAULT_VIEW))).to(device)
        generator = torch.Generator(device=device).manual_seed(int(params.get("seed", 0)))
        return reconstruct(network, diffusion, batch, cfg, generator)[0].float().cpu().numpy()


def logged_model(client, run_id: str, create: bool = False):
    """The run's logged model :data:`MODEL_NAME` (None: it logged none); with ``create``, made (and linked to the
    run as its output) if new."""
    from mlflow.entities import LoggedModelOutput

    experiment_id = client.get_run(run_id).info.experiment_id
    found = client.search_logged_models([experiment_id], max_results=1, filter_string=(
        f"name = '{MODEL_NAME}' AND source_run_id = '{run_id}'"))
    if found or not create:
        return found[0] if found else None
    model = client.create_logged_model(experiment_id, name=MODEL_NAME, source_run_id=run_id)
    client.log_outputs(run_id, [LoggedModelOutput(model.model_id, step=0)])
    return model


def log_model(client, run_id: str, checkpoint: Path, metadata: dict[str, Any]) -> str:
    """Log the inference checkpoint folder ``checkpoint`` as the MLflow model of run ``run_id``, replacing the
    files of an earlier call (one model per run, as ``runs:/<run id>/model`` names one); returns the model's id
    (``models:/<id>``).

    What ``mlflow.pyfunc.log_model`` does, through ``client`` alone: it would read MLflow's process-wide
    tracking URI, and make a new model at each call.

    Args:
        client: an ``MlflowClient`` (or :class:`sweeps.store.tracking.PatientClient`) of the run's store.
        checkpoint: a folder :func:`cdm.checkpoint.save_checkpoint` wrote, copied as the artifact ``checkpoint``.
        metadata: plain values the model's ``MLmodel`` file keeps (the step, the reproducibility record).
    """
    from mlflow.entities import LoggedModelStatus
    from mlflow.models import Model

    model = logged_model(client, run_id, create=True)
    with tempfile.TemporaryDirectory(prefix="cdm-mlflow-model-") as tmp:
        local = Path(tmp) / MODEL_NAME
        described = Model(artifact_path=model.artifact_location, model_uuid=model.model_id, run_id=run_id,
                          metadata=metadata, model_id=model.model_id)
        with warnings.catch_warnings():  # an example would make MLflow sample a cloud at each log to check it
            warnings.filterwarnings("ignore", message=".*input example.*", category=UserWarning)
            mlflow.pyfunc.save_model(str(local), python_model=__file__, signature=signature(), mlflow_model=described,
                                     artifacts={CHECKPOINT_ARTIFACT: str(checkpoint)},
                                     pip_requirements=[f"cdm-lab=={version('cdm-lab')}"])
        client.log_model_artifacts(model.model_id, str(local))
    client.finalize_logged_model(model.model_id, LoggedModelStatus.READY)
    return model.model_id


def model_checkpoint(folder: Path) -> Path:
    """The checkpoint folder inside a downloaded MLflow model ``folder`` (its ``MLmodel`` says where), or ``folder``
    itself when it holds no ``MLmodel`` (a checkpoint folder, as runs of 0.1.0 logged).

    Raises:
        ValueError: an ``MLmodel`` without the artifact, or placing it outside ``folder``; starts ``--checkpoint:``.
    """
    if not (folder / "MLmodel").is_file():
        return folder
    path: Any = read_mapping(folder / "MLmodel", "--checkpoint")  # the store's text: through the project's reader
    for key in ("flavors", "python_function", "artifacts", CHECKPOINT_ARTIFACT, "path"):
        path = path.get(key) if isinstance(path, dict) else None
    if not isinstance(path, str):
        raise ValueError(f"--checkpoint: {folder} is an MLflow model without a {CHECKPOINT_ARTIFACT!r} artifact; "
                         "give one a sweep trial logged (runs:/<run id>/model, models:/<name>/<version>)")
    inside = (folder / path).resolve()
    if not inside.is_relative_to(folder.resolve()):  # read nothing outside the model
        raise ValueError(f"--checkpoint: {folder}/MLmodel places its checkpoint outside the model ({inside})")
    return inside


set_model(PointCloudModel())
