"""External inputs of a run: the local files a config names (weights, depth maps, embeddings, images).

Nothing is downloaded at run time: a user fetches or computes these once (README, "External inputs").
:func:`required_inputs` lists what a config needs, :func:`missing_inputs` which paths are absent,
:func:`check_inputs` refuses the first absent one, and :func:`check_coverage` checks that a present
file or folder covers every object of the data sets — all before anything is written or started.

=============================  ==============================================  ======
field                          what                                            kind
=============================  ==============================================  ======
``model.encoder_weights``      MSN ViT-S/16 weights (``encoder: vit_s16``)     file
``model.global_embeddings``    per-object embeddings ``.npz``                  file
``priors.depth_maps``          estimated depth maps ``<object_id>/<pos>.npy``  folder
``data.condition_folder``      generated condition images                      folder
=============================  ==============================================  ======
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Literal, NamedTuple

from cdm.config import Config
from cdm.paths import input_path

__all__ = [
    "ExternalInput",
    "check_coverage",
    "check_inputs",
    "describe_inputs",
    "missing_inputs",
    "required_inputs",
]


class ExternalInput(NamedTuple):
    """One local file or folder a config reads.

    Attributes:
        field: the dotted config field naming it.
        path: as given (``~`` expanded).
        what: what it holds, in words.
        kind: ``file`` or ``folder``.
        source: where to get it.
    """

    field: str
    path: Path
    what: str
    kind: Literal["file", "folder"]
    source: str

    @property
    def present(self) -> bool:
        return self.path.is_file() if self.kind == "file" else self.path.is_dir()


def required_inputs(cfg: Config) -> list[ExternalInput]:
    """Every external input ``cfg`` reads, in config order."""
    out = []
    if cfg.model.encoder == "vit_s16":
        out.append(ExternalInput("model.encoder_weights", input_path(cfg.model.encoder_weights),
                                 "MSN ViT-S/16 weights", "file", "https://dl.fbaipublicfiles.com/msn/vits16_800ep.pth.tar"))
    if cfg.model.global_source == "embeddings":
        out.append(ExternalInput("model.global_embeddings", input_path(cfg.model.global_embeddings),
                                 "per-object global embeddings (.npz)", "file", "cdm/tools/openclip_embeddings.py"))
    if cfg.priors.prior_2d == "depth" and cfg.priors.depth_source == "maps" and cfg.priors.depth_maps is not None:
        out.append(ExternalInput("priors.depth_maps", input_path(cfg.priors.depth_maps),
                                 "estimated depth maps", "folder", "your depth estimator on `python -m cdm.tools.export_views` crops"))
    d = cfg.data
    if d.condition_folder is not None and (d.input_source == "folder" or (d.condition_views and d.condition_source == "folder")):
        out.append(ExternalInput("data.condition_folder", input_path(d.condition_folder),
                                 "generated condition images", "folder", "your generator on `python -m cdm.tools.export_views` renderings"))
    return out


def missing_inputs(cfg: Config) -> list[ExternalInput]:
    """The required inputs whose path does not exist (or is not a file / folder as it must be)."""
    return [i for i in required_inputs(cfg) if not i.present]


def check_inputs(cfg: Config) -> None:
    """Raise ``ValueError`` naming the first absent input's field, path and where to get it."""
    missing = missing_inputs(cfg)
    if missing:
        i = missing[0]
        unset = " — set the environment variable it names" if "$" in str(i.path) else ""
        raise ValueError(f"{i.field}: {i.path} does not exist{unset} (a {i.kind} of {i.what}; get it from {i.source})")


def describe_inputs(cfg: Config) -> str:
    """One line for a dry run: ``inputs: model.encoder_weights=PATH (ok), ...`` or ``inputs: none``."""
    items = [f"{i.field}={i.path} ({'ok' if i.present else 'MISSING'})" for i in required_inputs(cfg)]
    return "inputs: " + (", ".join(items) if items else "none (everything is generated or in data.root)")


def check_coverage(cfg: Config, datasets: Iterable) -> None:
    """Check that every object of ``datasets`` (their ``objects``: ``(category, object_id)``) has an
    entry in each external input that is keyed by object; ``ValueError`` names the field and an id."""
    from cdm.data.condition_images import ConditionImages
    from cdm.data.depth_maps import DepthMaps
    from cdm.model.embeddings import embedding_ids

    datasets = list(datasets)
    ids = [ref.object_id for ds in datasets for ref in ds.objects]
    for item in required_inputs(cfg):
        if item.field == "model.global_embeddings":
            have = embedding_ids(item.path)
            missing = [o for o in ids if o not in have]
            if missing:
                raise ValueError(f"model.global_embeddings: {item.path} has no embedding for object id {missing[0]!r} "
                                 f"({len(missing)} of {len(ids)} objects missing)")
        elif item.field == "priors.depth_maps":
            DepthMaps(item.path, cfg.priors.depth_maps_disparity).require(ids)
        elif item.field == "data.condition_folder":
            ConditionImages(item.path, cfg.data.condition_grey, by_position=any(ds.captured for ds in datasets)).require(ids)
