"""What the sweep package adds to ``cdm-lab`` (:mod:`cdm.lab`), through the entry points pyproject.toml names.

- :data:`COMMANDS` (``cdm_lab.commands``): the sweep commands, ``cdm-lab run SPEC`` being
  ``python sweeps/run.py SPEC``. Importing this module imports no command's module, so ``cdm-lab --help``
  stays free of torch, Ray and MLflow.
- :func:`fetch` (``cdm_lab.checkpoint_fetchers``): a model command's ``--checkpoint`` given as an MLflow
  artifact URI. ``cdm-lab evaluate --checkpoint runs:/<run id>/model`` (and ``reconstruct``) scores a sweep
  trial's weights where MLflow keeps them: MLflow resolves the URI (``runs:/``, ``models:/<name>/<version>`` of
  the registry, or the artifact store's own ``s3://…``, ``mlflow-artifacts:/…``) against ``MLFLOW_TRACKING_URI``
  and downloads the files into the folder :func:`cdm.lab.fetched_checkpoint` keeps while the command runs. A
  trial's MLflow model (:mod:`sweeps.mlflow_model`) holds its checkpoint as an artifact, which the command reads,
  as any local checkpoint, as safetensors and JSON (:func:`cdm.checkpoint.load_checkpoint`); a URI naming a
  checkpoint folder itself is read as it is. ``python -m cdm`` refuses a URI in one line naming ``cdm-lab``.
"""

from __future__ import annotations

from pathlib import Path

from cdm.lab import Command

__all__ = ["COMMANDS", "fetch"]

_SWEEPS = "sweeps: Ray, Optuna and MLflow around the model"
COMMANDS: dict[str, tuple[str, Command]] = {
    name: (_SWEEPS, Command(f"sweeps.{module}", summary, as_file=True))
    for name, module, summary in (
        ("run", "run", "run a sweep spec: its trials on Ray, tracked in MLflow, a results table"),
        ("report", "report", "rebuild a finished sweep's table, plots and panels from MLflow"),
        ("register", "register", "register a finished sweep's best cell's model in MLflow"),
        ("rerun", "rerun", "re-run one finished trial from its MLflow record, checked first"),
        ("inputs", "inputs", "a data set's inputs for the paper profile, made as Ray tasks"),
    )
}
"""The sweep commands, in the order ``cdm-lab --help`` lists them."""


def fetch(uri: str, folder: Path) -> Path:
    """The checkpoint folder of ``uri``'s files, downloaded by MLflow into ``folder``: inside an MLflow model
    (:func:`sweeps.mlflow_model.model_checkpoint`), or the files themselves.

    Raises:
        ValueError: MLflow could not resolve or download the URI, or its files hold no checkpoint; one line,
            naming the option, the URI and the cause.
    """
    import mlflow.artifacts
    from mlflow.exceptions import MlflowException

    from sweeps.mlflow_model import model_checkpoint

    try:
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=str(folder)))
    except (MlflowException, OSError) as exc:
        cause = " ".join(str(exc).split())[:300]
        raise ValueError(f"--checkpoint: MLflow could not fetch {uri} ({cause}); a sweep trial's weights are "
                         "runs:/<run id>/model, a registered one's models:/<name>/<version>, found with "
                         "MLFLOW_TRACKING_URI set to the sweep's store") from None
    return model_checkpoint(local)
