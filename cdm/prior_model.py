"""Unconditional category prior for BDM blending: PC²'s point-voxel denoiser without the image.

BDM (Xu et al., CVPR 2024) blends the reconstruction model with PVD, an unconditional point-cloud
diffusion model trained on one category's ground-truth clouds (paper Table 2, "+BDM"). Ours is the
reconstruction network's denoiser (``model.denoiser``; with ``pvcnn2`` PVD's own PVCNN2, sized by the
``model`` group) with no per-point conditioning channels, trained on the ``train`` split's clouds only — no
image is rendered, so a step costs a fraction of a CDM step.

Schedule: BDM's prior, PVD's linear β from 1e-4 to 0.02 over T = 1000 (BDM
``experiments/pvd/__init__.py``, ``prepare_pvd_model``), wherever the config does not set the
``diffusion`` field to another value than cdm's default; the target follows ``diffusion.prediction``
(PVD: ε).

A prior is a checkpoint folder (:mod:`cdm.checkpoint`: ``checkpoint.json`` with the resolved config, step,
voxel back-end, ``kind`` and ``category``; the weights in ``model.safetensors``); or PVD's own ``.pth``
checkpoint, as BDM blends with (:func:`load_prior`). ``python -m cdm train-prior`` writes one;
:func:`ensure_priors` trains and caches them for ``sampling.blend.prior_checkpoint: auto`` (sweep trials).
"""

from __future__ import annotations

import fcntl
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor, nn

from cdm.checkpoint import CHECKPOINT_FILE, Checkpoint, load_checkpoint, network_config, save_checkpoint
from cdm.config import Config, DiffusionConfig, ModelConfig
from cdm.data import build_dataset, list_categories
from cdm.data.order import batch_indices
from cdm.diffusion import GaussianDiffusion
from cdm.digest import json_digest
from cdm.model.pvcnn import PVCNNDenoiser
from cdm.model.pvcnn2 import PVCNN2Denoiser
from cdm.model.reference_weights import load_reference_checkpoint, load_reference_weights
from cdm.model.state_dicts import load_into
from cdm.model.voxels import VoxelBackend, resolve_voxel_backend
from cdm.optim import Optimiser, TrainingDiverged
from cdm.runtime import start_run

__all__ = [
    "AUTO",
    "PRIOR_KIND",
    "PRIOR_SCHEDULE",
    "CategoryPrior",
    "PriorNetwork",
    "PriorResult",
    "ensure_priors",
    "load_prior",
    "prior_config",
    "prior_path",
    "train_prior",
]

PRIOR_SCHEDULE = {"num_steps": 1000, "beta_start": 1e-4, "beta_end": 2e-2}
"""BDM's prior (PVD) schedule, ``diffusion`` fields a prior takes unless its config sets them."""
PRIOR_KIND = "category_prior"
"""``kind`` of a prior checkpoint; CDM checkpoints have none, so one cannot be mistaken for the other."""
AUTO = "auto"
"""``sampling.blend.prior_checkpoint`` value that asks a sweep trial to train the priors itself."""
_FIELD = "sampling.blend.prior_checkpoint"


class PriorNetwork(nn.Module):
    """Unconditional denoiser ``(x_t, t) → (B, N, 3)``: the ``model.denoiser`` with 0 conditioning channels.

    With ``pvcnn2`` it is PVD's unconditional PVCNN2 as BDM uses it (the same network as PC²'s on xyz
    alone), so PVD/BDM weights load into ``denoiser`` (:func:`cdm.model.load_reference_weights`).

    Args:
        cfg: the model group (denoiser; widths, voxel resolutions, back-end or PC²'s multipliers; time embedding).
        device: only resolves ``voxel_backend="auto"``, as in :class:`~cdm.model.CDMNetwork`.
    """

    def __init__(self, cfg: ModelConfig, *, device: torch.device | str | None = None):
        super().__init__()
        self.voxel_backend: VoxelBackend = resolve_voxel_backend(cfg.voxel_backend, device)
        self.denoiser: nn.Module
        if cfg.denoiser == "pvcnn2":
            self.denoiser = PVCNN2Denoiser(
                0, cfg.width_multiplier, cfg.voxel_resolution_multiplier, embed_dim=cfg.time_embed_dim
            )
        else:
            self.denoiser = PVCNNDenoiser(
                0, cfg.widths, cfg.voxel_resolutions, cfg.time_embed_dim, self.voxel_backend, cfg.devoxelize
            )

    def forward(self, x_t: Tensor, t: Tensor) -> Tensor:
        """``x_t (B, N, 3)`` world frame of the normalised object, ``t (B,)`` long → raw output ``(B, N, 3)``."""
        return self.denoiser(x_t, x_t.new_zeros(*x_t.shape[:2], 0), t)


class CategoryPrior(NamedTuple):
    """A loaded prior: network (eval mode, on its device), its own diffusion schedule, its category."""

    network: PriorNetwork
    diffusion: GaussianDiffusion
    category: str


class PriorResult(NamedTuple):
    """Where :func:`train_prior` wrote the prior and how training ended."""

    checkpoint: Path
    """The prior's checkpoint folder (:mod:`cdm.checkpoint`)."""
    steps: int
    loss: float
    """Mean diffusion loss over the last ``train.log_every`` steps."""
    seconds: float


def prior_config(config: Config, category: str) -> Config:
    """The config a prior of ``category`` trains with: ``config`` for that category alone, blending
    off, and BDM's prior schedule in every schedule field ``config`` leaves at cdm's default (PC²'s).

    Decided by value, not by whether a field was written, so a config read back from a checkpoint
    (where every field is written) gives the same prior.
    """
    default = DiffusionConfig()
    schedule = {
        f"diffusion.{k}": v for k, v in PRIOR_SCHEDULE.items() if getattr(config.diffusion, k) == getattr(default, k)
    }
    return config.replace(**schedule, **{"data.categories": [category], "sampling.blend.enabled": False})


def train_prior(
    config: Config, out_dir: str | Path, progress: Callable[[int, float], None] | None = None
) -> PriorResult:
    """Train a category prior on the ground-truth clouds of ``config``'s one category (from :func:`prior_config`).

    Uses ``train`` (steps, batch size, AdamW, warm-up + cosine, grad clip, seed, device, threads) and
    writes the checkpoint folder ``out_dir`` atomically at the end. ``progress(step, loss)`` is called every
    ``train.log_every`` steps.

    Raises:
        ValueError: unknown or more than one category (named ``data.categories``).
        TrainingDiverged: the loss became NaN or infinite.
    """
    categories = list_categories(config)
    if len(categories) != 1:
        raise ValueError(f"data.categories: a category prior models one category, got {list(categories)}")
    t = config.train
    device = start_run(t)
    data = build_dataset(config, "train")
    clouds = torch.stack([data.surface(i).cloud for i in range(len(data))])  # (K, N, 3), world frame in [-1, 1]³
    network = PriorNetwork(config.model, device=device).to(device)
    diffusion = GaussianDiffusion.from_config(config.diffusion)
    optimiser = Optimiser(network.parameters(), t)
    generator = torch.Generator(device=device).manual_seed(t.seed)
    start = time.perf_counter()
    window: list[float] = []
    for step in range(t.steps):
        x0 = clouds[[i for _, i in batch_indices(step, t.batch_size, len(clouds), t.seed)]].to(device)
        steps_t = torch.randint(0, diffusion.num_steps, (x0.shape[0],), generator=generator, device=device)
        noise = torch.randn(x0.shape, generator=generator, device=device)
        loss = diffusion.loss(network(diffusion.q_sample(x0, steps_t, noise), steps_t), x0, noise, steps_t)
        if not torch.isfinite(loss):
            raise TrainingDiverged(
                f"the category prior's loss became NaN or infinite at step {step}; lower train.lr (now {t.lr})"
            )
        optimiser.step(loss)
        window = (window + [loss.item()])[-t.log_every :]
        if progress is not None and ((step + 1) % t.log_every == 0 or step + 1 == t.steps):
            progress(step + 1, sum(window) / len(window))
    state = Checkpoint(config=config.to_dict(), step=t.steps, voxel_backend=network.voxel_backend,
                       model=network.state_dict(), kind=PRIOR_KIND, category=categories[0])
    folder = Path(out_dir)
    save_checkpoint(state, folder)
    return PriorResult(folder, t.steps, sum(window) / len(window) if window else math.nan, time.perf_counter() - start)


def prior_path(template: str, category: str) -> Path:
    """The prior of ``category`` named by ``sampling.blend.prior_checkpoint`` (``{category}`` filled in)."""
    if template == AUTO:
        raise ValueError(
            f"{_FIELD}: 'auto' is resolved inside sweep trials (one prior per category, trained and cached in the "
            "sweep folder); outside a sweep, train one with `python -m cdm train-prior --category <name>` "
            "and pass its folder"
        )
    return Path(template.replace("{category}", category))


def load_prior(path: str | Path, device: torch.device | str = "cpu", category: str = "") -> CategoryPrior:
    """Read a prior onto ``device``, in eval mode: a folder or ``checkpoint.json`` written by :func:`train_prior`,
    or a ``.pth`` file of PVD's (BDM's priors, the paper's Table 2), for ``category``.

    A PVD checkpoint (``model_state`` or ``prior_model``, alexzhou907/PVD ``train_generation.py``) is PVD's
    PVCNN2 at its defaults (multipliers 1, time embedding 64) with PVD's schedule (:data:`PRIOR_SCHEDULE`,
    ε-prediction). PVD trains on PointFlow's per-category global normalisation, the frame our ShapeNet
    loader hands out (:mod:`cdm.normalise`).

    Raises:
        ValueError: missing or unreadable file, or a checkpoint that is not a category prior; the
            message names ``sampling.blend.prior_checkpoint``.
    """
    if Path(path).suffix == ".pth":
        try:
            weights = load_reference_checkpoint(path, "pvd")
            network = PriorNetwork(ModelConfig(denoiser="pvcnn2", time_embed_dim=64))
            load_reference_weights(network.denoiser, weights)
        except (ValueError, OSError, RuntimeError) as exc:
            raise ValueError(f"{_FIELD}: {path}: not a PVD checkpoint we can read ({exc})") from None
        schedule = DiffusionConfig(**PRIOR_SCHEDULE, prediction="eps")
        return CategoryPrior(network.to(device).eval(), GaussianDiffusion.from_config(schedule), category)
    try:
        state = load_checkpoint(path)
    except ValueError as exc:
        raise ValueError(f"{_FIELD}: {exc}") from None
    if state.kind != PRIOR_KIND:
        raise ValueError(
            f"{_FIELD}: {path} is not a category prior (a CDM checkpoint?); train one with "
            "`python -m cdm train-prior --category <name>`"
        )
    cfg = network_config(state)
    network = PriorNetwork(cfg.model)
    load_into(network, state.model, f"{_FIELD}: {path}")
    return CategoryPrior(network.to(device).eval(), GaussianDiffusion.from_config(cfg.diffusion), state.category)


# What shapes a prior's weights: every group but those of evaluation, sampling and the 3D/2D priors
# (which change the images, not the clouds), and train fields that only say where and how it logs.
_NOT_IN_KEY = {
    "eval": None,
    "sampling": None,
    "priors": None,
    "train": ("out_dir", "threads", "device", "eval_every", "log_every"),
}


def _prior_key(config: Config) -> str:
    tree = prior_config(config, list_categories(config)[0]).to_dict()
    del tree["data"]["categories"]
    for group, fields in _NOT_IN_KEY.items():
        for name in fields or list(tree[group]):
            del tree[group][name]
    return json_digest(tree, 10)


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Exclusive lock on ``path`` across processes (released when the file closes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        yield


def ensure_priors(config: Config, cache_dir: str | Path, progress: Callable[[str], None] | None = None) -> Config:
    """Resolve ``sampling.blend.prior_checkpoint: auto`` by training (or reusing) one prior per category.

    Each prior trains with :func:`prior_config` of this run's config — the same training clouds, model
    sizes and ``train`` budget — into ``cache_dir/<category>-<key>``, ``key`` hashing everything that
    shapes its weights, so cells of a sweep that differ only in 2D/3D priors or blending share it. A
    file lock per prior makes concurrent trials wait for the one that trains it. ``progress`` gets one
    line per prior.

    Returns:
        ``config`` with ``prior_checkpoint`` = ``cache_dir/{category}-<key>``; ``config`` itself when
        blending is off or the checkpoint is not ``auto``.
    """
    blend = config.sampling.blend
    if not blend.enabled or blend.prior_checkpoint != AUTO:
        return config
    cache, key = Path(cache_dir), _prior_key(config)
    for category in list_categories(config):
        folder = cache / f"{category}-{key}"
        with _locked(cache / f"{category}-{key}.lock"):
            if (folder / CHECKPOINT_FILE).is_file():
                if progress is not None:
                    progress(f"category prior {category}: reusing {folder}")
                continue
            result = train_prior(prior_config(config, category), folder)
            if progress is not None:
                progress(f"category prior {category}: trained {result.steps} steps in {result.seconds:.1f} s "
                         f"(loss {result.loss:.4f}) → {folder}")
    return config.replace(**{"sampling.blend.prior_checkpoint": str(cache / f"{{category}}-{key}")})
