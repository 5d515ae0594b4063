"""Typed, validated configuration for CDM: one home and one documented default per hyperparameter.

Each group is a frozen pydantic model with ``extra="forbid"``, so an unknown key or a value of the
wrong type or range fails at load time with a message naming the dotted field (``priors.lambda_3d``).
Defaults are the paper's (CDM, CVPR 2025) or PC²'s where the paper is silent; units are stated per
field. Sizes that differ between a laptop and the paper live in sweep profiles, not here.

Use :func:`load_config` for a YAML file or nested dict plus ``key=value`` overrides, and
:meth:`Config.replace` to derive one config from another (validated the same way).
"""

from __future__ import annotations

import copy
import itertools
import typing
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cdm.io.yaml import parse_yaml, read_mapping

__all__ = [
    "BlendConfig",
    "Config",
    "ConfigError",
    "DataKind",
    "DataConfig",
    "Devoxelize",
    "DiffusionConfig",
    "EvalConfig",
    "F1_THRESHOLD",
    "ModelConfig",
    "PAPER_DATA_SETS",
    "PaperDataSet",
    "Prediction",
    "Prior2D",
    "PriorTimestep",
    "PriorsConfig",
    "RenderKind",
    "Sampler",
    "SamplingConfig",
    "Spacing",
    "TrainConfig",
    "apply_overrides",
    "config_field_paths",
    "format_validation_error",
    "load_config",
    "read_config_file",
    "parse_override",
]


F1_THRESHOLD = 0.01
"""τ of the F-score, on the squared nearest-neighbour distance (world units²): paper §4 Metrics, F-Score@0.01
as BDM's ``experiments/evaluation/evaluation_f1.py`` applies it. ``eval.f1_threshold``'s default and
:func:`cdm.metrics.chamfer_f1`'s."""


PaperDataSet = Literal["shapenet_r2n2", "co3d"]
"""The data sets the paper reports on, the captured kinds (photographs with known cameras): the kinds whose
entry in :data:`cdm.registry.DATA_SETS` says ``paper``."""
PAPER_DATA_SETS: tuple[PaperDataSet, ...] = typing.get_args(PaperDataSet)
DataKind = Literal["procedural", "meshes", PaperDataSet]
"""``data.kind``: a key of :data:`cdm.registry.DATA_SETS` (the entry holds its class and facts)."""
Devoxelize = Literal["trilinear", "nearest"]
Prediction = Literal["eps", "x0", "v"]
"""What the denoiser predicts (``diffusion.prediction``)."""
Sampler = Literal["ddim", "ddpm"]
"""``diffusion.sampler``: a key of :data:`cdm.registry.SAMPLERS`."""
Spacing = Literal["linspace", "trailing"]
"""Where DDIM's steps sit (``diffusion.timestep_spacing``)."""
RenderKind = Literal["depth", "planar"]
"""What the 3D prior constraint renders (``priors.render_kind``): a key of :data:`cdm.registry.RENDER_KINDS`."""
Prior2D = Literal["none", "contour", "depth"]
"""The 2D prior of the input image (``priors.prior_2d``): a key of :data:`cdm.registry.PRIORS_2D`."""
PriorTimestep = Literal["same_index", "log_snr"]
"""How BDM blending picks the prior's timestep (``sampling.blend.prior_timestep``)."""


class ConfigError(ValueError):
    """A configuration value or key is invalid; the message names the dotted field."""


class _Group(BaseModel):
    # allow_inf_nan=False: every float field (betas' items too) must be a finite number, so
    # priors.lambda_3d=.inf fails here instead of stopping the training at step 0.
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False)


class DataConfig(_Group):
    """What the model trains and evaluates on."""

    kind: DataKind = "procedural"
    """Data-set kind, a key of ``cdm.registry.DATA_SETS``. ``procedural`` is the embedded default (no files)."""
    root: str | None = None
    """Folder of the data set on disk (``meshes``: one sub-folder per category; ``shapenet_r2n2``: holds
    ShapeNetRendering/ and ShapeNetCore.v2.PC15k/; ``co3d``: one folder per category), or a folder
    written by ``python -m cdm prepare``. Unused by ``procedural``."""
    categories: tuple[str, ...] = ()
    """Categories to use; empty = every category the data set has."""
    num_points: int = Field(4096, ge=16)
    """Points per ground-truth cloud (default: the paper's on ShapeNet; Co3D's is in the paper profile)."""
    image_size: int = Field(224, ge=16, le=1024)
    """Side of the square input image and of every rendering, in pixels (default: the paper's)."""
    train_objects: int = Field(512, ge=1)
    """Objects per category in the training split (procedural; meshes use what is on disk)."""
    val_objects: int = Field(16, ge=1)
    """Held-out objects per category used for evaluation."""
    seed: int = 0
    """Seed of the procedural generator and of the object/split assignment."""
    eval_split: Literal["val", "test", "tune"] = "val"
    """Published split held out for evaluation (``shapenet_r2n2``: PC15k's folder; ``co3d``: the
    ``fewview_dev`` set list, PC²'s protocol: ``val``); training always reads ``train``. ``tune``
    (``procedural`` only): objects ``procedural/<category>/tune/<i>``, disjoint from ``val``'s, so a recipe
    search never scores on the objects a table reports."""
    num_workers: int = Field(0, ge=0)
    """Data-loader worker processes decoding training batches ahead of the step; 0 = in the training process."""
    condition_views: int = Field(0, ge=0, le=16)
    """Extra condition images per training sample, projected onto the points like the input image
    (supplementary Table 8, "ControlNet" section): rendered kinds show views 1…k of k + 1 evenly spaced
    in azimuth around the input view; captured kinds k of the object's input views, evenly spaced through
    them from the input view. Sampling sees the input image only, as in the paper."""
    condition_views_random: bool = False
    """Draw the number of extra views per sample uniformly in 1…``condition_views`` (Table 8 row 3)."""
    condition_source: Literal["gt", "folder"] = "gt"
    """Extra condition images: renderings of the object (GT) or generated ones from ``condition_folder``."""
    input_source: Literal["gt", "folder"] = "gt"
    """The input image itself: the data set's, or the generated one of ``condition_folder`` (Table 8 rows 4, 6, 7)."""
    condition_folder: str | None = None
    """Folder of generated condition images: ``<object_id>/<round>/<view>.png`` (rendered kinds) or
    ``<object_id>/<position>.png`` (captured kinds); docs/paper.md, "External inputs"."""
    condition_grey: bool = False
    """Use grey versions (ITU-R 601 luma in all three channels) of the generated images (Table 8 rows 4, 7)."""
    train_view: int | None = Field(None, ge=0, le=23)
    """ShapeNet only: the one R2N2 rendering (``00`` … ``23``) every training sample shows; null = any of
    the 24, drawn per view round. BDM trains on view 00 only (``which_view_from24: '00'`` in its
    ``experiments/config/structured.py``); the held-out input is view 00 either way."""
    mask_rgb: bool = False
    """Co3D only: multiply the RGB by the foreground mask (soft, at full resolution, before the crop):
    background black, as PC²'s ``mask_images=True`` (PyTorch3D's ``image_rgb *= fg_probability``)."""
    drop_outliers: bool = True
    """Co3D only: drop the cloud's points outside its 0.5–99.5 % quantile box widened by 10 % before
    sampling. PC² keeps every point (PyTorch3D's ``_load_pointcloud`` subsamples, nothing else)."""
    exclude_sequences: bool = False
    """Co3D only: leave out PC²'s bad and low-quality sequences (:mod:`cdm.data.co3d_lists`; hydrant 73,
    teddybear 295) from every split, as PC²'s ``experiments/dataset/__init__.py``."""
    frames_per_sequence: int | None = Field(None, ge=1)
    """Co3D only: input frames kept per sequence, chosen as PyTorch3D's ``JsonIndexDataset``
    (``n_frames_per_sequence``) before the split's set list is applied (a sequence whose chosen frames
    are all in another split drops out); null = every frame of the split's set list. PC²: 1."""

    @model_validator(mode="after")
    def _check_protocol(self) -> DataConfig:
        co3d_only = {
            "data.mask_rgb": self.mask_rgb,
            "data.drop_outliers": not self.drop_outliers,
            "data.exclude_sequences": self.exclude_sequences,
            "data.frames_per_sequence": self.frames_per_sequence is not None,
        }
        wrong = [name for name, changed in co3d_only.items() if changed and self.kind != "co3d"]
        if self.train_view is not None and self.kind != "shapenet_r2n2":
            wrong.insert(0, "data.train_view")
        if self.eval_split == "tune" and self.kind != "procedural":
            raise ValueError(f"data.eval_split: tune is the procedural data set's tuning split (got data.kind="
                             f"{self.kind}); allowed here: val, test")
        if wrong:
            only = "shapenet_r2n2" if wrong[0] == "data.train_view" else "co3d"
            raise ValueError(
                f"{wrong[0]}: only data.kind={only} reads it (got data.kind={self.kind}); leave it at its default"
            )
        return self


class ModelConfig(_Group):
    """Image encoder, projection conditioning and point-voxel denoiser (PC² architecture)."""

    encoder: Literal["cnn", "vit_s16"] = "cnn"
    """Image encoder (``cdm.model.encoder``): a small trainable CNN, or PC²'s frozen ViT-S/16 with MSN
    weights (needs ``encoder_weights``, ``feature_dim: 384`` and an image size that is a multiple of 16)."""
    encoder_weights: str | None = None
    """Local file of the ViT-S/16 weights for ``encoder: vit_s16``: MSN's published
    ``vits16_800ep.pth.tar`` (https://dl.fbaipublicfiles.com/msn/vits16_800ep.pth.tar), a state dict
    with its key names, or PC²'s checkpoint (its ``feature_model.model.*``); null with ``init_from`` reads
    ``init_from``. A checkpoint records its SHA-256 and refuses other weights."""
    init_from: str | None = None
    """PC²'s checkpoint, ``checkpoint-latest.pth`` as its ``experiments/main.py`` saves it (or its model
    state dict): the network starts from its weights, PVCNN2 and the frozen ViT-S/16 alike (weights only:
    no optimiser state). ``{category}`` becomes the run's one category (PC² trains one model per
    category). Needs ``denoiser: pvcnn2`` and ``encoder: vit_s16`` (``python -m cdm train --init-from``
    reads them from the file); the file is read as data, never run (:func:`cdm.io.torch.load_inert`)."""
    feature_dim: int = Field(32, ge=1)
    """Channels of the per-pixel image feature map projected onto points (PC² ViT-S: 384)."""
    raster_radius: float = Field(0.0075, gt=0.0, le=1.0)
    """Point radius in NDC units of the hard rasterizer used for projection conditioning (default: PC²'s)."""
    denoiser: Literal["pvcnn2", "pointvoxel"] = "pointvoxel"
    """The denoiser network. ``pvcnn2`` is the paper's (PC²'s PVCNN2 layer for layer, ``cdm.model.pvcnn2``:
    set abstraction, attention, feature propagation; 28.0 M parameters at PC²'s inputs); the paper profile
    selects it. ``pointvoxel`` (``cdm.model.pvcnn``) keeps every point at every block, is shaped by
    ``widths``/``voxel_resolutions``/``voxel_backend`` and stays the default so that small configs stay cheap."""
    width_multiplier: float = Field(1.0, gt=0.0)
    """PC²'s ``width_multiplier``, ``pvcnn2`` only: scales every channel width (each must stay a multiple of 8;
    e.g. 0.25, 0.5, 1). PC²: 1."""
    voxel_resolution_multiplier: float = Field(1.0, gt=0.0)
    """PC²'s ``voxel_resolution_multiplier``, ``pvcnn2`` only: scales its voxel resolutions 32/16/8. PC²: 1."""
    widths: tuple[int, ...] = (64, 128, 256)
    """Channels of the denoiser's point-voxel blocks (PC²-like: 64/128/256), ``pointvoxel`` only."""
    voxel_resolutions: tuple[int, ...] = (32, 16, 16)
    """Voxel grid side of each block, same length as ``widths`` (PVCNN: 32/16/8)."""
    voxel_backend: Literal["auto", "dense", "sparse"] = "auto"
    """Voxel branch: dense ``Conv3d`` or submanifold convolution on occupied voxels only."""
    devoxelize: Devoxelize = "trilinear"
    """How voxel features return to points."""
    time_embed_dim: int = Field(64, ge=4)
    """Sinusoidal timestep embedding size (default: PC²'s)."""
    global_feature: Literal["none", "concat", "cross_attention"] = "none"
    """Global image embedding added to every point (supplementary Table 7); ``none`` in the paper's CDM."""
    global_source: Literal["image_features", "embeddings"] = "image_features"
    """Where ``global_feature`` takes its vectors: pooled encoder features, or per-object vectors from
    ``global_embeddings`` (the paper's OpenCLIP text, image or depth-image embeddings)."""
    global_embeddings: str | None = None
    """``.npz`` of per-object embeddings for ``global_source: embeddings``: one float array per object id,
    shape ``(E,)`` or ``(T, E)`` (``T`` tokens), the same for all (``cdm/tools/openclip_embeddings.py``)."""
    mask_channels: bool = True
    """Project the input mask and its distance transform onto the points with the image channels
    (:func:`cdm.model.conditioning.conditioning_map`): PC²'s ``use_mask``/``use_distance_transform``
    (true in its ``experiments/config/structured.py``, its Co3D runs); BDM sets both false for ShapeNet.
    Off, no mask reaches the network with ``encoder: vit_s16`` (RGB only, as PC²'s and BDM's ViT); the
    small CNN (``encoder: cnn``) still reads it."""

    @model_validator(mode="after")
    def _check_blocks(self) -> ModelConfig:
        if len(self.widths) != len(self.voxel_resolutions) or not self.widths:
            raise ValueError(
                f"model.widths {self.widths} and model.voxel_resolutions {self.voxel_resolutions} "
                "must be non-empty and of the same length"
            )
        if min(self.widths) < 8 or min(self.voxel_resolutions) < 2:
            raise ValueError("model.widths must be >= 8 and model.voxel_resolutions >= 2")
        if self.init_from is not None and (self.denoiser, self.encoder) != ("pvcnn2", "vit_s16"):
            raise ValueError(
                f"model.init_from: PC²'s weights need model.denoiser=pvcnn2 and model.encoder=vit_s16 (got "
                f"{self.denoiser}, {self.encoder}); `python -m cdm train --init-from FILE` sets PC²'s network"
            )
        if self.encoder == "vit_s16" and self.encoder_weights is None and self.init_from is None:
            raise ValueError(
                "model.encoder_weights is required with model.encoder=vit_s16: download MSN's ViT-S/16 weights "
                "(https://dl.fbaipublicfiles.com/msn/vits16_800ep.pth.tar) and pass the local path"
            )
        if self.encoder == "vit_s16" and self.feature_dim != 384:
            raise ValueError(f"model.feature_dim must be 384 with model.encoder=vit_s16 (got {self.feature_dim})")
        if self.global_source == "embeddings" and (self.global_embeddings is None or self.global_feature == "none"):
            raise ValueError(
                "model.global_source=embeddings needs model.global_embeddings (an .npz path) and "
                "model.global_feature concat or cross_attention"
            )
        return self


class DiffusionConfig(_Group):
    """Forward process, training target and sampler (DDPM as in PC²)."""

    num_steps: int = Field(1000, ge=2)
    """Diffusion steps T (default: PC²'s)."""
    beta_start: float = Field(1e-5, gt=0.0, lt=1.0)
    """First beta of the linear schedule (default: PC²'s)."""
    beta_end: float = Field(8e-3, gt=0.0, lt=1.0)
    """Last beta of the linear schedule (default: PC²'s)."""
    prediction: Prediction = "eps"
    """What the network predicts: ε as in the paper (Eq. 2–3), x₀, or v = √ᾱ ε − √(1−ᾱ) x₀."""
    sampler: Sampler = "ddim"
    """Evaluation sampler: DDIM (η=0) over ``sample_steps`` or ancestral DDPM (all T steps, or ``ddpm_steps``)."""
    sample_steps: int = Field(50, ge=1)
    """Steps of the DDIM sampler."""
    ddpm_steps: int | None = Field(None, ge=1)
    """Steps of the DDPM sampler: null takes all T (PC²'s ``num_inference_steps`` 1,000); fewer take every
    (T // n)-th timestep from 0, as diffusers' ``DDPMScheduler.set_timesteps``, each step drawn from the
    posterior between its two timesteps (β = 1 − ᾱ_t / ᾱ_prev) — quicker, not PC²'s numbers."""
    timestep_spacing: Spacing = "linspace"
    """Where the DDIM steps sit: ``linspace`` ends with a prediction at t = 0, ``trailing`` at
    t = T/sample_steps − 1 (Lin et al., 2024; better for x₀-prediction, ``cdm.diffusion``); DDPM ignores it."""
    clip_x0: float | None = Field(1.0, gt=0.0)
    """Clamp x̂₀ to [-clip_x0, clip_x0] while sampling; null = off. 1 fits the procedural and mesh-folder
    frames (their objects lie in [-1, 1]³, ``cdm.normalise``), not ShapeNet's (BDM's σ units: |x| past 2
    on the test fixture) nor Co3D's (world units): use null there, as the paper profile does."""

    @model_validator(mode="after")
    def _check_schedule(self) -> DiffusionConfig:
        if self.beta_end <= self.beta_start:
            raise ValueError("diffusion.beta_end must be greater than diffusion.beta_start")
        if self.sample_steps > self.num_steps or (self.ddpm_steps or 0) > self.num_steps:
            raise ValueError("diffusion.sample_steps and diffusion.ddpm_steps must be <= diffusion.num_steps")
        return self


class PriorsConfig(_Group):
    """The paper's two kinds of priors (§3.2 3D prior constraint, §3.3 2D priors)."""

    prior_3d: bool = True
    """Add the 3D prior constraint (Eq. 6) to the loss."""
    lambda_3d: float = Field(1.0, ge=0.0)
    """λ, dimensionless weight of the 3D prior constraint in the loss (Eq. 6)."""
    num_views: int = Field(10, ge=0)
    """H, views rendered for the constraint, evenly spaced from the input view (Table 5: 10 best)."""
    point_size: float = Field(0.04, gt=0.0, le=1.0)
    """The point size of the constraint's renderings (default: the paper's, §4), NDC units (one pixel is 2/S): the
    point radius of PyTorch3D's point rasteriser, each point's footprint integrated over the pixels
    (:func:`cdm.render.splat_points`)."""
    render_kind: RenderKind = "depth"
    """Constraint images: soft depth maps (Co3D) or planar point images (ShapeNet), Fig. 3."""
    depth_layer: float | None = Field(0.4, gt=0.0)
    """Depth maps only: thickness (view depth in the data set's frame units, ``cdm.normalise``; measured on
    objects of half-extent 1) of the front layer drawn, as PyTorch3D's z-buffer keeps the nearest point;
    null averages front and back surfaces
    (:func:`cdm.render.splat_points`). 0.4 came nearest a naive z-buffered reference of the ones measured
    (``benchmarks/RESULTS.md``, "Depth renders")."""
    render_size: int = Field(224, ge=8, le=1024)
    """Side of the constraint renderings in pixels (default: the paper's)."""
    target: Literal["x0_hat", "x_t_literal"] = "x0_hat"
    """Cloud compared with x₀: the predicted clean cloud x̂₀ (trainable) or x_t as Eq. 6 is written."""
    prior_2d: Prior2D = "contour"
    """2D prior concatenated with the image features (Eq. 7): contour (ShapeNet) or depth (Co3D)."""
    depth_source: Literal["ground_truth", "maps"] = "ground_truth"
    """Depth of the ``depth`` prior: the data set's own depth map (an **upper bound**: privileged, not
    estimated from the image) or estimated maps from ``depth_maps`` (the paper: DINOv2), captured data sets."""
    depth_maps: str | None = None
    """Folder of estimated depth maps for ``depth_source: maps``: ``<object_id>/<position>.npy`` (docs/paper.md,
    "External inputs"); any per-image scale and shift (normalised away per image). Null: the maps stored
    in a root prepared with ``python -m cdm prepare --depth-maps DIR``."""
    depth_maps_disparity: bool = False
    """The maps hold disparity (larger = nearer, e.g. Depth Anything's output), inverted before use."""

    @model_validator(mode="after")
    def _check_views(self) -> PriorsConfig:
        if self.prior_3d and self.num_views < 1:
            raise ValueError("priors.num_views (H) must be >= 1 when priors.prior_3d is on")
        return self


class TrainConfig(_Group):
    """Optimiser and loop: PC²'s AdamW with linear warm-up and cosine decay; every default is PC²'s."""

    steps: int = Field(100_000, ge=1)
    """Optimiser steps (default: PC²'s ``max_steps``)."""
    batch_size: int = Field(8, ge=1)
    """Objects per step (default: the paper's)."""
    lr: float = Field(1e-3, gt=0.0)
    """Peak AdamW learning rate, reached after ``warmup_steps`` (default: PC²'s)."""
    weight_decay: float = Field(1e-6, ge=0.0)
    """AdamW weight decay."""
    betas: tuple[float, float] = (0.95, 0.999)
    """AdamW betas (default: PC²'s)."""
    warmup_steps: int = Field(2000, ge=0)
    """Steps of linear warm-up before the cosine decay to zero at ``steps`` (default: PC²'s)."""
    grad_clip: float = Field(50.0, gt=0.0)
    """Largest global L2 norm of the gradient; larger gradients are scaled down to it (default: PC²'s)."""
    precision: Literal["fp32", "fp16", "bf16"] = "fp32"
    """Arithmetic of the network's forward and backward (PC²: ``fp16``, ``RunConfig.mixed_precision`` in
    ``experiments/config/structured.py``, through Accelerate; the paper profile sets it). ``fp16``: torch
    autocast to float16 with a dynamic loss scale (2¹⁶ at the start, halved on a step whose gradients hold
    inf or NaN, doubled after 2,000 finite steps: ``torch.amp.GradScaler``'s defaults, as Accelerate uses
    them); ``bf16``: autocast to bfloat16, no scale. Both skip the optimiser and schedule step whose
    gradients are not finite (the batch is consumed, the step counter advances; ``train/skipped_steps``
    counts them) and stop with ``TrainingDiverged`` after 32 skipped steps in a row; a non-finite loss
    stops the run in every precision, as PC²'s loop does. Only the image encoder and the denoiser run under
    autocast; these stay float32: the projection of x_t onto the input image (which point sees which
    pixel), the voxel averaging (scatter-mean), the distances of farthest-point sampling, ball query and
    the 3-NN search, the diffusion arithmetic, the losses, the weights, the optimiser and the metrics.
    Evaluation samples in the same precision (PC² samples through the same autocast-wrapped forward).
    ``fp16`` needs CUDA: on another device the run says so once and trains in ``fp32``. The checkpoint
    records the precision the run trained in; a resume in another precision says so once and continues
    (the loss scale restarts at 2¹⁶ when fp16 begins) rather than refusing, as precision changes the
    rounding, not the function."""
    ema_decay: float | None = Field(None, ge=0.0, lt=1.0)
    """Exponential moving average of weights used for evaluation; null = off."""
    eval_every: int = Field(5000, ge=1)
    """Evaluate (and checkpoint) every this many steps, and at the end."""
    compute_budget_s: float | None = Field(None, gt=0.0)
    """Seconds of compute training may spend before it stops (evaluates, checkpoints, ends), whichever of this
    and ``steps`` comes first; null = ``steps`` alone. On CPU: the training process's CPU seconds
    (``time.process_time``, all its threads), so runs sharing cores get the compute they used, not the wall time
    they waited; on CUDA: wall seconds of the training steps on the GPU (synchronised before each reading).
    Evaluation is not counted. The cosine decay still ends at ``steps`` (:func:`cdm.optim.lr_factor`); the
    spent seconds restart from 0 on a resume."""
    eval_every_s: float | None = Field(None, gt=0.0)
    """Also evaluate (and checkpoint) each time training's compute passes a multiple of this many seconds (the
    unit of ``compute_budget_s``): a sweep's rungs in seconds; null = by ``eval_every`` steps only."""
    log_every: int = Field(50, ge=1)
    """Report the running training loss every this many steps."""
    seed: int = 0
    """Seed of weights, batches and noise."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where to train; ``auto`` takes CUDA when present."""
    threads: int | None = Field(None, ge=1)
    """CPU threads for torch; null = torch's default."""
    out_dir: str = "runs/cdm"
    """Folder for checkpoints and evaluation outputs."""


class EvalConfig(_Group):
    """Held-out evaluation: which objects, on how many points (BDM's metrics, ``cdm.metrics``), in the data
    set's frame as it is (``cdm.normalise``: BDM's units on ShapeNet, PC²'s on Co3D)."""

    protocol: Literal["quick", "paper"] = "quick"
    """Which held-out objects are scored, one sample each. ``quick``: the first ``eval.num_objects`` per
    category (a fixed subset, comparable across cells, not the paper's numbers). ``paper``: every object
    of the references' evaluation split — BDM scores every ShapeNet object of the R2N2 ``test`` split
    (``data.eval_split: test``), PC² every Co3D ``fewview_dev`` ``val`` sequence."""
    num_objects: int = Field(16, ge=1)
    """Held-out objects per category scored under ``eval.protocol: quick``."""
    num_points: int = Field(4096, ge=16)
    """Points drawn from prediction and ground truth before the metrics: BDM scores 4,096 on ShapeNet
    (``dataset.max_points=4096`` in its ``experiments/example_sample.sh``), PC² 16,384 on Co3D (its
    ``max_points``)."""
    f1_threshold: float = Field(F1_THRESHOLD, gt=0.0)
    """F-score threshold applied to squared nearest-neighbour distance (paper and BDM: :data:`F1_THRESHOLD`)."""
    seed: int = 1234
    """Sampling seed, identical across runs so cells are compared on the same noise."""
    save_clouds: int = Field(4, ge=0)
    """Categories drawn per evaluation: the first evaluated object of each, up to this many, gets a PNG
    panel and PLY clouds (prediction, ground truth, each baseline). Drawing never changes a score."""
    retrieval_bank: int = Field(64, ge=1)
    """Training images per category searched by the nearest-image retrieval baseline."""
    only: bool = False
    """Score the network as it starts, with ``model.init_from``'s weights, once at step 0 and stop
    (``train.steps`` is not run): a table's PC² row from PC²'s released weights instead of a retrained PC²."""


class BlendConfig(_Group):
    """BDM blending at sampling time (Xu et al., CVPR 2024; the paper's Table 2 "+BDM"); see :mod:`cdm.blend`.

    In each window both this model and an unconditional category prior (:mod:`cdm.prior_model`)
    denoise the same x_t, then every point is taken from one of the two results at random; between
    windows this model samples alone. Milestones and windows count timesteps of the T-step schedule.
    """

    enabled: bool = False
    """Blend with a category prior while sampling (evaluation and ``reconstruct``); off = plain CDM / PC²."""
    prior_checkpoint: str | None = None
    """Prior from ``python -m cdm train-prior``: its folder or file. ``{category}`` in the path becomes each
    object's category (a path without it serves every object); ``auto``: a sweep trial trains one per
    category (``cdm.prior_model.ensure_priors``). Required when enabled."""
    milestones: tuple[int, ...] = (936, 872, 128, 64, 32)
    """Timesteps where a window starts, BDM's numbering (T = pure noise, 0 = clean), each in
    [window_steps, T], windows disjoint. BDM's ShapeNet run passes [1000, 968, 936, 872, 128, 64, 32, 0]
    and its loop blends at these five."""
    window_steps: int = Field(16, ge=1)
    """Timesteps per window (BDM's ``roll_step``: 16). A DDIM step belongs to a window when the
    timesteps it jumps over meet the window's."""
    select_prob: float = Field(0.5, ge=0.0, le=1.0)
    """Probability that a point is taken from the prior at the end of a window (BDM: 0.5, a fair coin)."""
    seed: int = 0
    """Seed of the per-point selection and of the prior branch's DDPM noise; apart from the sampling
    seed, so select_prob 0 reproduces the plain sampler exactly."""
    prior_timestep: PriorTimestep = "same_index"
    """Timestep the prior is evaluated at for the reconstruction's x_t: ``same_index`` passes the same t, as
    BDM's ``experiments/main_blending.py`` (its ``prior_milestones``), though the two schedules' noise
    levels differ; ``log_snr`` the prior schedule's t of nearest log-SNR (:func:`cdm.blend.matched_timesteps`)."""

    @model_validator(mode="after")
    def _check_windows(self) -> BlendConfig:
        if self.enabled and self.prior_checkpoint is None:
            raise ValueError(
                "sampling.blend.prior_checkpoint is required when sampling.blend.enabled is true; train one with "
                "`python -m cdm train-prior --category <name>` (or use auto inside a sweep)"
            )
        ordered = sorted(self.milestones, reverse=True)
        if len(set(ordered)) != len(ordered):
            raise ValueError(f"sampling.blend.milestones: repeated values in {list(self.milestones)}")
        close = [(a, b) for a, b in itertools.pairwise(ordered) if a - b < self.window_steps]
        if close:
            raise ValueError(
                f"sampling.blend.milestones: windows of {self.window_steps} steps starting at {close[0][0]} and "
                f"{close[0][1]} overlap; keep milestones at least sampling.blend.window_steps apart"
            )
        return self


class SamplingConfig(_Group):
    """Sampling-time additions to the diffusion sampler (``diffusion.sampler``)."""

    blend: BlendConfig = BlendConfig()
    """BDM blending with a category prior (paper Table 2)."""


class Config(_Group):
    """The whole resolved configuration of one training run."""

    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    diffusion: DiffusionConfig = DiffusionConfig()
    priors: PriorsConfig = PriorsConfig()
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()
    sampling: SamplingConfig = SamplingConfig()

    @model_validator(mode="after")
    def _check_external_inputs(self) -> Config:
        data = self.data
        uses_folder = "folder" in (data.input_source, data.condition_source if data.condition_views else "gt")
        if uses_folder and data.condition_folder is None:
            raise ValueError(
                "data.condition_folder is required when data.input_source or data.condition_source is folder"
            )
        if self.model.encoder == "vit_s16" and data.image_size % 16:
            raise ValueError(
                f"data.image_size must be a multiple of 16 with model.encoder=vit_s16 (got {data.image_size})"
            )
        if self.priors.depth_source == "maps" and data.kind not in PAPER_DATA_SETS:
            raise ValueError(
                f"priors.depth_source=maps needs a captured data set (data.kind {' or '.join(PAPER_DATA_SETS)}): "
                f"rendered kinds ({data.kind}) draw a fresh view every round, which no folder of maps can cover"
            )
        return self

    @model_validator(mode="before")
    @classmethod
    def _category_of_init_from(cls, tree: Any) -> Any:
        """``{category}`` in ``model.init_from`` becomes the run's one category, before validation, so
        every reader (inputs, network, protocol card) sees the file that is read."""
        model = tree.get("model") if isinstance(tree, dict) else None
        path = model.get("init_from") if isinstance(model, dict) else None
        if not isinstance(path, str) or "{category}" not in path:
            return tree
        categories = (tree.get("data") or {}).get("categories") or ()
        if isinstance(categories, str) or len(categories) != 1:
            raise ValueError(f"model.init_from: {{category}} in {path!r} needs exactly one data.categories entry "
                             f"(got {list(categories) if not isinstance(categories, str) else categories!r})")
        return {**tree, "model": {**model, "init_from": path.replace("{category}", str(categories[0]))}}

    @model_validator(mode="after")
    def _check_init_only(self) -> Config:
        if self.eval.only and self.model.init_from is None:
            raise ValueError("eval.only scores the weights a run starts from: set model.init_from to PC²'s checkpoint")
        return self

    @model_validator(mode="after")
    def _check_blend_schedule(self) -> Config:
        blend, t = self.sampling.blend, self.diffusion.num_steps
        outside = [m for m in blend.milestones if not blend.window_steps <= m <= t]
        if blend.enabled and outside:
            raise ValueError(
                f"sampling.blend.milestones: {outside} outside the schedule; each milestone starts a window of "
                f"sampling.blend.window_steps={blend.window_steps} timesteps and must lie in "
                f"[{blend.window_steps}, diffusion.num_steps={t}] ({t} = pure noise, 0 = clean)"
            )
        return self

    def to_dict(self) -> dict[str, Any]:
        """Nested plain-python dict (tuples as lists), loadable again by :func:`load_config`."""
        return self.model_dump(mode="json")

    def replace(self, **dotted: Any) -> Config:
        """A copy with dotted fields set, validated like :func:`load_config` (the one way to derive a config).

        Example: ``cfg.replace(**{"train.out_dir": path, "model.voxel_backend": "sparse"})``.

        Raises:
            ConfigError: unknown field or bad value; the message names the dotted field.
        """
        return load_config(self.to_dict(), dotted)

    def flat(self) -> dict[str, Any]:
        """Flat ``{"priors.lambda_3d": 1.0, "sampling.blend.enabled": False, ...}`` view, e.g. for tracking params."""
        tree = self.to_dict()
        out: dict[str, Any] = {}
        for path in config_field_paths():
            value: Any = tree
            for part in path.split("."):
                value = value[part]
            out[path] = value
        return out


def format_validation_error(err: ValidationError, schema: type[BaseModel]) -> str:
    """One readable line for a pydantic error of ``schema``: ``loc: message; loc: message``.

    An unknown key lists the fields allowed where it stands (list indices and dict keys in ``loc``
    are stepped over); a wrong literal shows the value given. Shared by configs and sweep specs.
    """
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            msg = f"unknown key; allowed: {', '.join(_fields_at(schema, e['loc'][:-1]))}"
        elif e["type"] == "literal_error":
            msg = f"{msg} (got {e['input']!r})"
        lines.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(lines)


def _model_in(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _fields_at(schema: type[BaseModel], loc: tuple) -> list[str]:
    model = schema
    for part in loc:
        if isinstance(part, str) and part in model.model_fields:
            model = _model_in(model.model_fields[part].annotation) or model
    return list(model.model_fields)


def _leaf_fields(model: type[BaseModel], prefix: str) -> list[str]:
    out = []
    for name, info in model.model_fields.items():
        if isinstance(info.annotation, type) and issubclass(info.annotation, _Group):
            out += _leaf_fields(info.annotation, f"{prefix}{name}.")
        else:
            out.append(f"{prefix}{name}")
    return out


def config_field_paths(group: str | None = None) -> list[str]:
    """Dotted names of every config field (``["data.kind", ..., "sampling.blend.enabled", ...]``),
    optionally of one group (``priors``) or nested group (``sampling.blend``)."""
    paths = _leaf_fields(Config, "")
    return paths if group is None else [p for p in paths if p.startswith(f"{group}.")]


def parse_override(text: str) -> tuple[str, Any]:
    """Parse ``key=value`` where value is YAML (``priors.point_size=0.04``, ``data.categories=[a,b]``), read
    under the one YAML rule of :mod:`cdm.io.yaml`."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like key=value, e.g. priors.lambda_3d=0.5")
    key, raw = text.split("=", 1)
    try:
        value = parse_yaml(raw, f"{key}: the value")
    except ValueError as exc:  # over a cap of cdm.io.yaml, not YAML, or a value Python refuses
        raise ConfigError(str(exc)) from None
    return key.strip(), value


def apply_overrides(tree: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Return a copy of nested ``tree`` with dotted-key ``overrides`` set; unknown paths are errors."""
    known = set(config_field_paths())
    out = copy.deepcopy(tree)  # nested groups too (sampling.blend): the caller's tree stays untouched
    for key, value in overrides.items():
        if key not in known:
            raise ConfigError(f"{key}: unknown config field; see `python -m cdm fields` for the list")
        *groups, name = key.split(".")
        section = out
        for i, group in enumerate(groups):
            section = section.setdefault(group, {})
            if not isinstance(section, dict):
                raise ConfigError(f"{'.'.join(groups[: i + 1])}: must be a mapping")
        section[name] = value
    return out


def read_config_file(path: str | Path) -> Any:
    """The YAML tree of a config file, read under the one YAML rule of :mod:`cdm.io.yaml` (not yet validated).

    Raises:
        ConfigError: missing, unreadable, too large, too deeply nested or not YAML; the message names the file.
    """
    try:
        return read_mapping(Path(path), "config file")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def load_config(source: str | Path | dict[str, Any] | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """Build a validated :class:`Config` from a YAML path or nested dict plus dotted overrides.

    Raises:
        ConfigError: unreadable file, unknown key or bad value; the message names the field.
    """
    if source is None:
        tree: dict[str, Any] = {}
    elif isinstance(source, dict):
        tree = source
    else:
        tree = read_config_file(source)
    if not isinstance(tree, dict):
        raise ConfigError("config: top level must be a mapping of groups (data, model, ...)")
    tree = apply_overrides(tree, overrides or {})
    try:
        return Config.model_validate(tree)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, Config)) from None
