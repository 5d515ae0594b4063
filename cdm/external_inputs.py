"""External inputs of a run: the local files a config names (weights, depth maps, embeddings, images).

Nothing is downloaded at run time: a user fetches or computes these once (docs/paper.md, "External inputs").
:func:`required_inputs` lists what a config needs, :func:`missing_inputs` which paths are absent,
:func:`check_inputs` refuses the first absent one, and :func:`check_coverage` checks that a present
file or folder covers every object of the data sets — all before anything is written or started.

=============================  ==============================================  ======
field                          what                                            kind
=============================  ==============================================  ======
``model.encoder_weights``      MSN ViT-S/16 weights (``encoder: vit_s16``)     file
``model.init_from``            PC²'s checkpoint (PVCNN2 and its ViT-S/16)      file
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
from cdm.registry import PRIORS_2D

__all__ = [
    "MSN_URL",
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
        source: the command that makes it (the user runs it: nothing is downloaded at run time).
    """

    field: str
    path: Path
    what: str
    kind: Literal["file", "folder"]
    source: str

    @property
    def present(self) -> bool:
        return self.path.is_file() if self.kind == "file" else self.path.is_dir()


MSN_URL = "https://dl.fbaipublicfiles.com/msn/vits16_800ep.pth.tar"
"""MSN's ViT-S/16 (PC²'s ``vit_small_patch16_224_msn``), which a user fetches once."""


def required_inputs(cfg: Config) -> list[ExternalInput]:
    """Every external input ``cfg`` reads, in config order; ``source`` is the command that makes it."""
    out = []
    export = "python -m cdm.tools.export_views --out views/ " + " ".join(
        f"--set data.{k}={v}" for k, v in (("kind", cfg.data.kind), ("root", cfg.data.root)) if v is not None)
    if cfg.model.init_from is not None:
        out.append(ExternalInput("model.init_from", input_path(cfg.model.init_from), "PC²'s checkpoint", "file",
                                 "PC²'s released checkpoint-latest.pth, or one its experiments/main.py wrote"))
    if cfg.model.encoder == "vit_s16" and cfg.model.encoder_weights is not None:
        path = input_path(cfg.model.encoder_weights)
        out.append(ExternalInput("model.encoder_weights", path, "MSN ViT-S/16 weights", "file",
                                 f"curl -L --create-dirs -o {cfg.model.encoder_weights} {MSN_URL}"))
    if cfg.model.global_source == "embeddings":
        out.append(ExternalInput("model.global_embeddings", input_path(cfg.model.global_embeddings),
                                 "per-object global embeddings (.npz)", "file",
                                 f"{export}, then python -m cdm.tools.openclip_embeddings --views views/ "
                                 f"--kind text|image|depth --npz {cfg.model.global_embeddings}"))
    reads_maps = PRIORS_2D[cfg.priors.prior_2d].reads_depth and cfg.priors.depth_source == "maps"
    if reads_maps and cfg.priors.depth_maps is not None:
        out.append(
            ExternalInput(
                "priors.depth_maps",
                input_path(cfg.priors.depth_maps),
                "estimated depth maps",
                "folder",
                f"{export}, then python -m cdm.tools.estimate_depth --views views/ --model "
                f"<DPT or Depth Anything folder> --out {cfg.priors.depth_maps}",
            )
        )
    d = cfg.data
    if d.condition_folder is not None and (
        d.input_source == "folder" or (d.condition_views and d.condition_source == "folder")
    ):
        out.append(
            ExternalInput(
                "data.condition_folder",
                input_path(d.condition_folder),
                "generated condition images",
                "folder",
                f"{export} --rounds R, then your generator on the point renderings, writing "
                f"{d.condition_folder}/<object_id>/<round>/<view>.png (docs/paper.md, 'External inputs')",
            )
        )
    return out


def missing_inputs(cfg: Config) -> list[ExternalInput]:
    """The required inputs whose path does not exist (or is not a file / folder as it must be)."""
    return [i for i in required_inputs(cfg) if not i.present]


def check_inputs(*configs: Config) -> None:
    """Raise ``ValueError`` naming every input absent for any of ``configs``, once each: its field, path
    and the command that makes it."""
    missing = {(i.field, str(i.path)): i for cfg in configs for i in missing_inputs(cfg)}
    if missing:
        def say(i: ExternalInput) -> str:
            unset = " — set the environment variable it names" if "$" in str(i.path) else ""
            return f"{i.field}: {i.path} does not exist{unset} (a {i.kind} of {i.what}; make it with: {i.source})"

        raise ValueError("; ".join(say(i) for i in missing.values()))


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
            ConditionImages(
                item.path, cfg.data.condition_grey, by_position=any(ds.captured for ds in datasets)
            ).require(ids)
