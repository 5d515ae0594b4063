"""The references' value of every config field, per paper table and data set: what the protocol card diffs against.

A result is comparable with the paper's only where its resolved config equals what the paper or its
reference code fixed. This module is that record, field by field, each value with its source:

- the paper (CDM, CVPR 2025; section, table or equation of ``/work/shared/paper``'s text);
- PC² (lukemelas/projection-conditioned-point-cloud-diffusion), the code the paper builds on and the
  reference on Co3D (Tables 3–5, Supp. Tables 7–8);
- BDM (mlpc-ucsd/BDM), the reference on ShapeNet (Tables 1–2): its ShapeNet data set, scripts and
  blending loop, with the PC² model it trains.

Every field of :func:`cdm.config.config_field_paths` has one :data:`Entry` in each record: :class:`Stated`,
:class:`NotStated` or :class:`NoEffect`. A record may name fields the config does not have (yet): the card
lists a stated one as a deviation (this code cannot be set to the reference).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from cdm.config import PAPER_DATA_SETS, Config, PaperDataSet
from sweeps.plan.profiles import load_profiles

__all__ = ["DATA_SETS", "RECORDS", "TABLES", "Entry", "Kind", "NoEffect", "NotStated", "Stated", "record", "show"]

Kind = PaperDataSet
DATA_SETS = PAPER_DATA_SETS
"""The data sets the paper reports on (:data:`cdm.config.PaperDataSet`); which tables ran on which is the spec's
``datasets:`` section."""

TABLES = ("Table 1", "Table 2", "Table 3", "Table 4", "Table 5", "Table 6", "Supp. Table 7", "Supp. Table 8")
"""Tables with a record, named as a spec's ``paper.table``."""

_PC2 = "PC² experiments/config/structured.py"
_BDM = "BDM experiments/config/structured.py"
_BDM_TRAIN = "BDM experiments/example_train.sh"


def show(value: Any) -> str:
    """A config value as the card prints it: YAML's spelling (``null``, ``true``, ``[a, b]``), floats by ``:g``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(show(v) for v in value) + "]"
    return str(value)


class _Conditional:
    """An entry read only where the config's other fields hold one of the values its ``when`` allows."""

    when: Mapping[str, tuple[Any, ...]]

    def applies(self, flat: Mapping[str, Any]) -> bool:
        return all(k in flat and flat[k] in allowed for k, allowed in self.when.items())


@dataclass(frozen=True)
class Stated(_Conditional):
    """A value the paper or a reference code fixes, in this config's terms (as :meth:`Config.flat` gives it)."""

    value: Any
    source: str
    """Where it is fixed: the paper's section / table / equation, or the reference repository's file."""
    when: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
    """Other fields' values under which this one is read; elsewhere it is not compared. A field the
    config does not have fails the condition."""
    accepts: Callable[[Any], bool] | None = None
    """For a source that fixes a property rather than one value (``value`` then describes it)."""

    def holds(self, value: Any) -> bool:
        return self.accepts(value) if self.accepts is not None else value == self.value

    @property
    def shown(self) -> str:
        return self.value if self.accepts is not None else show(self.value)


@dataclass(frozen=True)
class NotStated(_Conditional):
    """No source fixes this field: a free choice of ours."""

    why: str
    noted: bool = False
    """Name the choice on the card (those that shape a result and a reader could not guess)."""
    when: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
    """As :attr:`Stated.when`: where the field is read, so where the note applies."""


@dataclass(frozen=True)
class NoEffect:
    """A field that changes where or how fast a run goes, or which random draw it takes, not its protocol."""

    why: str


Entry = Stated | NotStated | NoEffect

_DEFAULT: Any = object()
"""A :class:`Stated` value that is the field's default in :mod:`cdm.config`, the value's one home (its
docstring names the source too); :func:`record` puts it in, so no paper value is written both there and here."""
_PAPER: Any = object()
"""A :class:`Stated` value that the paper profile of ``sweeps/profiles.yaml`` sets (its ``overrides``, then its
fields for the record's data set), where the reference differs from the config default: that profile is the
value's one home."""


@functools.cache
def _values(kind: Kind) -> dict[str, Any]:
    """Where :data:`_DEFAULT` and :data:`_PAPER` values live: the config defaults, then the paper profile's."""
    paper = load_profiles()["paper"]
    return {"default": Config().flat(), "paper": {**paper.overrides, **paper.datasets.get(kind, {})}}


def _read(path: str, entry: Entry, kind: Kind) -> Entry:
    if not isinstance(entry, Stated) or not (entry.value is _DEFAULT or entry.value is _PAPER):
        return entry
    return replace(entry, value=_values(kind)["default" if entry.value is _DEFAULT else "paper"][path])

_PRIOR_3D = {"priors.prior_3d": (True,)}
_BLEND = {"sampling.blend.enabled": (True,)}
_PATH = NoEffect("a path on this machine")
_DRAW = NoEffect("which random draw; the references fix none")

_COMMON: dict[str, Entry] = {
    # data
    "data.root": _PATH,
    "data.image_size": Stated(_DEFAULT, "paper §4 Implementation Details"),
    "data.train_objects": NotStated("the procedural generator's size; published data sets bring their splits"),
    "data.val_objects": NotStated("the procedural generator's size; published data sets bring their splits"),
    "data.seed": _DRAW,
    "data.num_workers": NoEffect("data-loader processes"),
    "data.condition_views": Stated(_DEFAULT, "paper Supp. Table 8 row 1: the single input image, as PC²"),
    "data.condition_views_random": Stated(_DEFAULT, "paper Supp. Table 8 row 1"),
    "data.condition_source": Stated(_DEFAULT, "paper Supp. Table 8 row 1"),
    "data.input_source": Stated(_DEFAULT, "paper Supp. Table 8 row 1: the data set's image"),
    "data.condition_folder": _PATH,
    "data.condition_grey": Stated(_DEFAULT, "paper Supp. Table 8 row 1"),
    # model
    "model.denoiser": Stated(_PAPER, "PC² experiments/model/point_cloud_model.py: PVCNN2"),
    "model.width_multiplier": Stated(
        _DEFAULT, "PC² experiments/model/point_cloud_model.py", {"model.denoiser": ("pvcnn2",)}
    ),
    "model.voxel_resolution_multiplier": Stated(
        _DEFAULT, "PC² experiments/model/point_cloud_model.py", {"model.denoiser": ("pvcnn2",)}
    ),
    "model.encoder": Stated(_PAPER, f"{_PC2}: image_feature_model vit_small_patch16_224_msn, frozen"),
    "model.encoder_weights": NoEffect("a path; a checkpoint records the weights' SHA-256"),
    "model.feature_dim": Stated(_PAPER, f"{_PC2}: ViT-S/16's channels"),
    "model.raster_radius": Stated(_DEFAULT, "PC² experiments/model/projection_model.py: raster_point_radius"),
    "model.widths": NotStated("our point-voxel denoiser's shape; PC²'s PVCNN2 fixes its own"),
    "model.voxel_resolutions": NotStated("our point-voxel denoiser's shape; PC²'s PVCNN2 fixes its own"),
    "model.voxel_backend": NotStated("how voxel convolutions are computed"),
    "model.devoxelize": NotStated("our point-voxel denoiser's devoxelisation"),
    "model.time_embed_dim": Stated(_DEFAULT, f"{_PC2}: point_cloud_model_embed_dim"),
    "model.global_feature": Stated(
        _DEFAULT, "paper §3.3: global embeddings gave no gain; PC² use_global_features False"
    ),
    "model.global_source": NotStated("read only with model.global_feature (Supp. Table 7 sweeps it)"),
    "model.global_embeddings": _PATH,
    "model.init_from": Stated(
        _DEFAULT,
        "PC² experiments/main.py: each table's model trained from scratch by its recipe",
        {"eval.only": (False,)},
    ),
    # diffusion
    "diffusion.num_steps": Stated(_DEFAULT, "PC² experiments/model/model.py: diffusers' training timesteps"),
    "diffusion.beta_start": Stated(_DEFAULT, f"{_PC2}: beta_start"),
    "diffusion.beta_end": Stated(_DEFAULT, f"{_PC2}: beta_end"),
    "diffusion.prediction": Stated(_DEFAULT, "paper Eq. 3 and 6: ε-prediction"),
    "diffusion.sampler": Stated(_PAPER, f"{_PC2}: diffusion_scheduler ddpm"),
    "diffusion.sample_steps": Stated(1000, f"{_PC2}: num_inference_steps", {"diffusion.sampler": ("ddim",)}),
    "diffusion.ddpm_steps": Stated(
        _DEFAULT, f"{_PC2}: num_inference_steps 1000, every timestep", {"diffusion.sampler": ("ddpm",)}
    ),
    "diffusion.timestep_spacing": NotStated(
        "DDIM's step placement; the references sample with DDPM", noted=True, when={"diffusion.sampler": ("ddim",)}
    ),
    "diffusion.clip_x0": Stated(_PAPER, "PC² experiments/model/model.py: DDPMScheduler(clip_sample=False)"),
    # priors
    "priors.prior_3d": Stated(_DEFAULT, "paper §3.2: CDM trains with the 3D prior constraint"),
    "priors.lambda_3d": Stated(
        _DEFAULT, "paper Eq. 6: the prior term has unit weight (Eq. 5's λ is the ELBO's)", _PRIOR_3D
    ),
    "priors.num_views": Stated(_DEFAULT, "paper Table 5: the best H (the F1 of Table 3's CDM, teddybear)", _PRIOR_3D),
    "priors.point_size": Stated(_DEFAULT, "paper §4 Implementation Details", _PRIOR_3D),
    "priors.depth_layer": Stated(
        "a front layer (PyTorch3D's z-buffer keeps the nearest point)",
        "paper §4: PyTorch3D renders the 3D prior images",
        {**_PRIOR_3D, "priors.render_kind": ("depth",)},
        accepts=lambda v: v is not None,
    ),
    "priors.render_size": Stated(_DEFAULT, "paper §4 Implementation Details", _PRIOR_3D),
    "priors.target": Stated(
        _DEFAULT,
        "paper §3.2: the term is back-propagated as a regulariser; x_t as Eq. 6 writes it carries no gradient",
        _PRIOR_3D,
    ),
    "priors.depth_source": Stated(
        _PAPER, "paper §3.3: depth estimated from the image (DINOv2)", {"priors.prior_2d": ("depth",)}
    ),
    "priors.depth_maps": _PATH,
    "priors.depth_maps_disparity": NoEffect("the maps' file format, converted on reading"),
    # train
    "train.steps": Stated(_DEFAULT, f"{_PC2}: max_steps"),
    "train.lr": Stated(_DEFAULT, f"{_PC2}: OptimizerConfig.lr"),
    "train.weight_decay": Stated(_DEFAULT, f"{_PC2}: AdamOptimizerConfig.weight_decay"),
    "train.betas": Stated(_DEFAULT, f"{_PC2}: AdamOptimizerConfig betas"),
    "train.warmup_steps": Stated(_DEFAULT, f"{_PC2}: CosineSchedulerConfig num_warmup_steps"),
    "train.grad_clip": Stated(_DEFAULT, f"{_PC2}: clip_grad_norm"),
    "train.ema_decay": Stated(_DEFAULT, f"{_PC2}: use_ema False"),
    "train.precision": Stated(
        _PAPER, f"{_PC2}: RunConfig.mixed_precision 'fp16', Accelerate's autocast and loss scale"
    ),
    "train.compute_budget_s": Stated(_DEFAULT, f"{_PC2}: max_steps, a training length in steps (no compute budget)"),
    "train.eval_every": NoEffect("when to score; the final score is at train.steps"),
    "train.eval_every_s": NoEffect("when to score; the final score is at the end of training"),
    "train.log_every": NoEffect("logging"),
    "train.seed": _DRAW,
    "train.device": NoEffect("where it runs"),
    "train.threads": NoEffect("CPU threads"),
    "train.out_dir": _PATH,
    # eval
    "eval.protocol": Stated(
        _PAPER, "PC² and BDM experiments/config/structured.py: num_sample_batches None, every object of the split"
    ),
    "eval.num_objects": NotStated("the quick protocol's subset", when={"eval.protocol": ("quick",)}),
    "eval.f1_threshold": Stated(
        _DEFAULT, "paper §4 Metrics: the F-Score's threshold; BDM experiments/evaluation/evaluation_f1.py"
    ),
    "eval.seed": _DRAW,
    "eval.save_clouds": NoEffect("drawings; no score changes"),
    "eval.retrieval_bank": NoEffect("a baseline's search, not the model's score"),
    "eval.only": NotStated(
        "PC²'s released weights (model.init_from) scored instead of a retrained PC²",
        noted=True,
        when={"eval.only": (True,)},
    ),
    # sampling.blend
    "sampling.blend.enabled": Stated(
        _DEFAULT, "paper Tables 1, 3–6: sampled without BDM (only Table 2's +BDM rows blend)"
    ),
    "sampling.blend.prior_checkpoint": Stated(
        "PVD's checkpoint from BDM's repository",
        "paper §4: PVD as the pre-trained prior, checkpoints from BDM's code",
        _BLEND,
        accepts=lambda v: str(v).endswith(".pth"),
    ),  # cdm.prior_model.load_prior
    "sampling.blend.milestones": Stated(_DEFAULT, "BDM experiments/example_sample_blending.sh", _BLEND),
    "sampling.blend.window_steps": Stated(_DEFAULT, "BDM experiments/example_sample_blending.sh: roll_step", _BLEND),
    "sampling.blend.select_prob": Stated(
        _DEFAULT, "BDM experiments/main_blending.py: torch.randint(0, 2) per point", _BLEND
    ),
    "sampling.blend.seed": _DRAW,
    "sampling.blend.prior_timestep": Stated(_DEFAULT, "BDM experiments/main_blending.py: prior_milestones", _BLEND),
}

_SHAPENET_ONLY = {"data.kind": ("shapenet_r2n2",)}
_CO3D_ONLY = {"data.kind": ("co3d",)}


def _one_category(categories: list[str]) -> bool:
    """One model per category, as both references train (an empty list means every category at once)."""
    return len(categories) == 1


_SHAPENET: dict[str, Entry] = {
    "data.kind": Stated("shapenet_r2n2", "paper §4: ShapeNet, R2N2 renderings with PC15k clouds as BDM"),
    "data.categories": Stated("one category per model", f"{_BDM_TRAIN}: dataset.category", accepts=_one_category),
    "data.num_points": Stated(_DEFAULT, "paper §4; BDM experiments/example_train.sh: dataset.max_points"),
    "data.eval_split": Stated(
        "test", "BDM experiments/dataset/shapenet_r2n2.py: R2N2's test split (pc_dict_v2.json)", _SHAPENET_ONLY
    ),
    "data.train_view": Stated(_PAPER, f"{_BDM}: which_view_from24 '00'", _SHAPENET_ONLY),
    "data.mask_rgb": NoEffect("Co3D only"),
    "data.drop_outliers": NoEffect("Co3D only"),
    "data.exclude_sequences": NoEffect("Co3D only"),
    "data.frames_per_sequence": NoEffect("Co3D only"),
    "model.mask_channels": Stated(_PAPER, f"{_BDM}: use_mask and use_distance_transform False"),
    "priors.prior_2d": Stated(_DEFAULT, "paper §4.1 ShapeNet: contour as the 2D prior"),
    "priors.render_kind": Stated("planar", "paper §4.1 ShapeNet: planar point images in the 3D prior", _PRIOR_3D),
    "train.batch_size": Stated(_PAPER, f"{_BDM_TRAIN}: dataloader.batch_size; the paper states none"),
    "train.precision": Stated(
        _PAPER, f"{_BDM}: RunConfig.mixed_precision 'fp16', Accelerate's autocast and loss scale"
    ),
    "eval.num_points": Stated(_DEFAULT, "BDM experiments/example_sample.sh: dataset.max_points"),
}

_CO3D: dict[str, Entry] = {
    "data.kind": Stated("co3d", "paper §4: Co3D v2 as PC²"),
    "data.categories": Stated("one category per model", f"{_PC2}: CO3DConfig.category", accepts=_one_category),
    "data.num_points": Stated(_PAPER, f"paper §4; {_PC2}: max_points"),
    "data.eval_split": Stated(_DEFAULT, f"{_PC2}: eval_split val of subset fewview_dev", _CO3D_ONLY),
    "data.train_view": NoEffect("ShapeNet only"),
    "data.mask_rgb": Stated(_PAPER, f"{_PC2}: CO3DConfig.mask_images = use_mask", _CO3D_ONLY),
    "data.drop_outliers": Stated(
        _PAPER, "PC² experiments/dataset/__init__.py: PyTorch3D's loader, every point", _CO3D_ONLY
    ),
    "data.exclude_sequences": Stated(
        _PAPER, "PC² experiments/dataset/__init__.py: EXCLUDE_SEQUENCE, LOW_QUALITY_SEQUENCE", _CO3D_ONLY
    ),
    "data.frames_per_sequence": Stated(
        _PAPER, "PC² experiments/dataset/__init__.py: n_frames_per_sequence=1", _CO3D_ONLY
    ),
    "model.mask_channels": Stated(_DEFAULT, f"{_PC2}: use_mask and use_distance_transform True"),
    "priors.prior_2d": Stated("depth", "paper §1, §3.3: depth estimated from real-world images"),
    "priors.render_kind": Stated(_DEFAULT, "paper §3.2, Fig. 2: depth images of the clouds", _PRIOR_3D),
    "train.batch_size": Stated(_DEFAULT, f"{_PC2}: DataloaderConfig.batch_size; the paper states none"),
    "eval.num_points": Stated(_PAPER, f"{_PC2}: max_points"),
}

RECORDS: dict[Kind, dict[str, Entry]] = {"shapenet_r2n2": _SHAPENET, "co3d": _CO3D}
"""Each paper data set's own entries (:data:`cdm.config.PaperDataSet`; ``tests/test_registry.py`` holds it
complete against the ``paper`` entries of :data:`cdm.registry.DATA_SETS`)."""

_PC2_ROWS: dict[str, Entry] = {
    "priors.prior_3d": Stated(False, "paper Supp. Tables 7–8: every row is PC² plus its addition"),
    "priors.prior_2d": Stated("none", "paper Supp. Tables 7–8: every row is PC² plus its addition"),
}

_TABLES: dict[str, dict[str, Entry]] = {
    "Supp. Table 7": _PC2_ROWS,
    "Supp. Table 8": _PC2_ROWS,
}
"""What a table changes in its data set's record (Tables 1–6 are the paper's CDM and PC² on it)."""


def record(table: str | None, kind: Kind) -> dict[str, Entry]:
    """The reference record of ``table`` (a spec's ``paper.table``; None: the paper's CDM) on data set ``kind``.

    Raises:
        KeyError: a table without a record (add it to :data:`TABLES` and its changes here).
    """
    if table is not None and table not in TABLES:
        raise KeyError(f"{table!r}: no reference record; tables with one: {', '.join(TABLES)}")
    entries = {**_COMMON, **RECORDS[kind], **_TABLES.get(table or "", {})}
    return {path: _read(path, e, kind) for path, e in entries.items()}
