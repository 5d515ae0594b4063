"""A model command's ``--checkpoint`` given as an MLflow artifact URI, fetched by MLflow before the command reads it.

``cdm-lab evaluate --checkpoint runs:/<run id>/model`` (and ``reconstruct``) scores a sweep trial's weights where
MLflow keeps them: MLflow resolves the URI (``runs:/``, ``models:/<name>/<version>`` of the registry, or the
artifact store's own ``s3://…``, ``mlflow-artifacts:/…``) against ``MLFLOW_TRACKING_URI`` and downloads the files
into a temporary folder. A trial's MLflow model (:mod:`sweeps.mlflow_model`) holds its checkpoint as an artifact,
which the command reads, as any local checkpoint, as safetensors and JSON
(:func:`cdm.checkpoint.load_checkpoint`); a URI naming a checkpoint folder itself is read as it is. The model
library itself knows nothing of MLflow (docs/ARCHITECTURE.md): ``python -m cdm`` refuses a URI in one line that
names this command.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cdm.paths import names_a_uri

__all__ = ["FetchError", "fetched_checkpoint"]

_OPTION = "--checkpoint"


class FetchError(Exception):
    """The URI could not be fetched; the message names the option, the URI and the cause."""


def _checkpoint_value(argv: list[str]) -> tuple[int, str] | None:
    """(index in ``argv``, value) of ``--checkpoint VALUE`` or ``--checkpoint=VALUE``; None when absent."""
    for i, arg in enumerate(argv):
        if arg == _OPTION and i + 1 < len(argv):
            return i + 1, argv[i + 1]
        if arg.startswith(_OPTION + "="):
            return i, arg.removeprefix(_OPTION + "=")
    return None


def _fetch(uri: str, folder: Path) -> str:
    """The checkpoint folder of ``uri``'s files, downloaded by MLflow into ``folder``: inside an MLflow model
    (:func:`sweeps.mlflow_model.model_checkpoint`), or the files themselves."""
    import mlflow.artifacts
    from mlflow.exceptions import MlflowException

    from sweeps.mlflow_model import model_checkpoint

    try:
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=str(folder)))
    except (MlflowException, OSError) as exc:
        cause = " ".join(str(exc).split())[:300]
        raise FetchError(f"{_OPTION}: MLflow could not fetch {uri} ({cause}); a sweep trial's weights are "
                         "runs:/<run id>/model, a registered one's models:/<name>/<version>, found with "
                         "MLFLOW_TRACKING_URI set to the sweep's store") from None
    try:
        return str(model_checkpoint(local))
    except ValueError as exc:
        raise FetchError(str(exc)) from None


@contextmanager
def fetched_checkpoint(argv: list[str]) -> Iterator[list[str]]:
    """``argv`` with a ``--checkpoint`` URI replaced by the folder MLflow downloaded it to, kept while the
    context lasts; ``argv`` unchanged when it names a local checkpoint (MLflow is then not even imported).

    Raises:
        FetchError: MLflow could not resolve or download the URI.
    """
    found = _checkpoint_value(argv)
    if found is None or not names_a_uri(found[1]):
        yield argv
        return
    i, uri = found
    with tempfile.TemporaryDirectory(prefix="cdm-checkpoint-") as tmp:
        local = _fetch(uri, Path(tmp))
        yield [*argv[:i], local if argv[i] == uri else f"{_OPTION}={local}", *argv[i + 1:]]
