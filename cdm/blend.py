"""BDM blending at sampling time (Xu et al., "Bayesian Diffusion Model for 3D Shape Reconstruction",
CVPR 2024), the "+BDM" rows of the paper's Table 2.

The reconstruction model samples as usual (DDIM or DDPM, :class:`~cdm.diffusion.GaussianDiffusion`).
At each milestone a window opens: from the same x_t, the reconstruction model and an unconditional
category prior (:mod:`cdm.prior_model`) each take the sampler's steps through the window, then every
point is taken from one of the two results at random (BDM-Blending; BDM ``main_blending.py``)::

    x_rec ← step(x_rec, x̂₀_rec(x_rec, t)),  x_pri ← step(x_pri, x̂₀_pri(x_pri, t))   each step of the window
    x ← s ⊙ x_pri + (1 − s) ⊙ x_rec,   s_{b,n} ~ Bernoulli(select_prob), one draw per point

Between windows the reconstruction model runs alone.

**Windows.** Milestones use BDM's numbering on the T-step schedule (T = pure noise, 0 = clean): the
window of milestone m covers timesteps m−1 … m−w (w = ``window_steps``), i.e. x_m → x_{m−w}. A
sampler step from t to t_prev stands for timesteps t … t_prev+1 and belongs to the window when these
meet the window's: with DDPM that is exactly w steps; with DDIM, the one or two steps whose jump
covers the window (BDM's own DDIM mode likewise blends one DDIM step of ≈16 timesteps). A step an
earlier window took is not taken again.

**Noise levels.** The prior keeps its own schedule (BDM's: β 1e-4 → 0.02, against PC²'s 1e-5 → 8e-3).
BDM hands the prior the same x_t *and the same timestep index* (``main_blending.py``: the prior runs
from ``prior_milestones[i + 1]``, the reconstruction's milestone itself under DDPM), although ᾱ_t
differs between the two schedules; ``sampling.blend.prior_timestep: same_index`` (the default) does
the same. ``log_snr`` instead evaluates the prior at the timestep of its schedule whose log-SNR is
nearest to that of the reconstruction model's ᾱ_t (:func:`matched_timesteps`; identical schedules:
the same t). Either way both branches take the reconstruction sampler's step from their x̂₀, so both
end the window at the same noise level.

**Randomness.** The reconstruction branch draws from the sampling ``generator`` exactly as
:meth:`GaussianDiffusion.sample` does; the prior branch's DDPM noise and the selection draw from a
separate ``blend_generator``. So ``select_prob`` 0 reproduces the plain sampler bit for bit.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from cdm.config import Config, PriorTimestep
from cdm.data.sample import Batch
from cdm.diffusion import GaussianDiffusion, ModelFn, SamplerSettings
from cdm.prior_model import CategoryPrior, load_prior, prior_path

__all__ = [
    "BlendResult",
    "blend_windows",
    "blended_reconstruction",
    "blended_sample",
    "matched_timesteps",
    "prior_timesteps",
]

PriorX0Fn = Callable[[Tensor, Tensor], Tensor]
"""``prior_x0(x_t (B, N, 3), t (B,) long, reconstruction timesteps) -> the prior's x̂₀ (B, N, 3)``."""


class BlendResult(NamedTuple):
    """Blended samples and, per window in sampling order, which points came from the prior."""

    points: Tensor
    """``(B, N, 3)`` final clouds, world frame of the normalised object."""
    from_prior: tuple[Tensor, ...]
    """One ``(B, N)`` bool mask per window: True where the point was taken from the prior branch."""


def blend_windows(timesteps: Sequence[int], milestones: Sequence[int], window_steps: int) -> list[tuple[int, ...]]:
    """Indices into the sampler's ``timesteps`` (descending) of each window's steps, in sampling order.

    Step ``i`` goes from ``timesteps[i]`` to the next timestep (−1 after the last) and stands for
    timesteps ``t … t_prev+1``; it belongs to the window of milestone ``m`` when that range meets
    ``m−1 … m−window_steps``. Windows left with no step (their steps taken by an earlier one) are dropped.
    """
    claimed: set[int] = set()
    windows = []
    for m in sorted(milestones, reverse=True):
        steps = []
        for i, t in enumerate(timesteps):
            t_prev = timesteps[i + 1] if i + 1 < len(timesteps) else -1
            if i not in claimed and t >= m - window_steps and t_prev + 1 <= m - 1:
                steps.append(i)
        claimed.update(steps)
        if steps:
            windows.append(tuple(steps))
    return windows


def matched_timesteps(alphas_cumprod: Tensor, prior_alphas_cumprod: Tensor) -> Tensor:
    """For every timestep of a schedule ``(T,)``, the prior schedule's ``(T',)`` timestep of nearest
    log-SNR, log(ᾱ / (1 − ᾱ)): ``(T,)`` long. Equal schedules map each t to itself."""

    def log_snr(a: Tensor) -> Tensor:
        return torch.log(a) - torch.log1p(-a)

    return (log_snr(alphas_cumprod)[:, None] - log_snr(prior_alphas_cumprod)[None, :]).abs().argmin(dim=1)


def prior_timesteps(
    alphas_cumprod: Tensor, prior_alphas_cumprod: Tensor, mode: PriorTimestep
) -> Tensor:
    """``(T,)`` long: the prior's timestep for each reconstruction timestep (``sampling.blend.prior_timestep``).

    Args:
        alphas_cumprod: ``(T,)`` ᾱ of the reconstruction schedule.
        prior_alphas_cumprod: ``(T',)`` ᾱ of the prior's schedule.
        mode: ``same_index`` (BDM: t itself; needs T' = T) or ``log_snr`` (:func:`matched_timesteps`).
    """
    if mode == "log_snr":
        return matched_timesteps(alphas_cumprod, prior_alphas_cumprod)
    if len(prior_alphas_cumprod) != len(alphas_cumprod):
        raise ValueError(
            f"sampling.blend.prior_timestep: same_index needs a prior of {len(alphas_cumprod)} timesteps, "
            f"this one has {len(prior_alphas_cumprod)}; use log_snr or train the prior on diffusion.num_steps"
        )
    return torch.arange(len(alphas_cumprod))


_SETTINGS = SamplerSettings()
"""The plain sampler's settings (the config defaults'), ``blended_sample``'s default."""


def blended_sample(
    diffusion: GaussianDiffusion,
    model_fn: ModelFn,
    prior_x0: PriorX0Fn,
    shape: tuple[int, int, int],
    *,
    generator: torch.Generator | None,
    blend_generator: torch.Generator | None,
    milestones: Sequence[int],
    window_steps: int,
    select_prob: float,
    settings: SamplerSettings = _SETTINGS,
    device: torch.device | str = "cpu",
    progress: Callable[[int, int], None] | None = None,
) -> BlendResult:
    """:meth:`GaussianDiffusion.sample` with BDM blending windows (module docstring).

    Args:
        diffusion: the reconstruction model's schedule; both branches take its sampler's steps.
        model_fn: reconstruction model, ``(x_t, t) -> raw output`` as for ``sample``.
        prior_x0: the prior's clean estimate for the reconstruction timestep (``sampling.blend.prior_timestep``).
        shape: ``(B, N, 3)``.
        generator: sampling noise (x_T and the reconstruction branch's DDPM noise).
        blend_generator: the prior branch's DDPM noise and the per-point selection.
        milestones, window_steps, select_prob: ``sampling.blend`` (checked by the config).
        settings, device, progress: as for ``sample``; ``settings.clip_x0`` clamps both x̂₀.
    """
    x = torch.randn(shape, generator=generator, device=device)
    # The same timesteps and step functions as GaussianDiffusion.sample, so that outside windows
    # (and everywhere at select_prob 0) every operation on x is the plain sampler's.
    timesteps = diffusion.timesteps(settings)
    windows = blend_windows(timesteps, milestones, window_steps)
    opens = {w[0] for w in windows}
    closes = {w[-1] for w in windows}

    def step(x_t: Tensor, t: Tensor, i: int, x0_hat: Tensor, gen: torch.Generator | None) -> Tensor:
        return diffusion.step(x_t, t, i, timesteps, x0_hat, settings, gen)

    x_prior: Tensor | None = None
    masks = []
    for i, t_int in enumerate(timesteps):
        t = torch.full((shape[0],), t_int, dtype=torch.long, device=device)
        if i in opens:
            x_prior = x  # both branches start from the same x_t (steps never modify x in place)
        x_next = step(x, t, i, diffusion.predict_x0(x, t, model_fn(x, t)), generator)
        if x_prior is not None:
            x_prior = step(x_prior, t, i, prior_x0(x_prior, t), blend_generator)
        if i in closes:
            take = torch.rand(shape[:2], generator=blend_generator, device=device) < select_prob  # (B, N)
            x_next = torch.where(take[..., None], x_prior, x_next)
            masks.append(take)
            x_prior = None
        x = x_next
        if progress is not None:
            progress(i + 1, len(timesteps))
    return BlendResult(x, tuple(masks))


def _prior_x0_fn(priors: dict[str, CategoryPrior], categories: Sequence[str], diffusion: GaussianDiffusion,
                 mode: PriorTimestep) -> PriorX0Fn:
    """x̂₀ of each object's category prior, evaluated at the timestep :func:`prior_timesteps` gives."""
    groups = []
    for category, prior in priors.items():
        index = torch.tensor([j for j, c in enumerate(categories) if c == category])
        groups.append((prior, index, prior_timesteps(diffusion.alphas_cumprod, prior.diffusion.alphas_cumprod, mode)))

    def prior_x0(x_t: Tensor, t: Tensor) -> Tensor:
        out = torch.empty_like(x_t)
        for prior, index, matched in groups:
            idx = index.to(x_t.device)
            t_prior = matched[t[idx].cpu()].to(x_t.device)
            x = x_t[idx]
            out[idx] = prior.diffusion.predict_x0(x, t_prior, prior.network(x, t_prior))
        return out

    return prior_x0


def blended_reconstruction(
    model_fn: ModelFn,
    diffusion: GaussianDiffusion,
    batch: Batch,
    cfg: Config,
    generator: torch.Generator,
    progress: Callable[[int, int], None] | None = None,
) -> BlendResult:
    """Blended sampling of one reconstruction per object of ``batch`` with ``cfg.sampling.blend``.

    Loads each category's prior (``prior_checkpoint`` with ``{category}`` filled in; a path without it
    serves every object). The blend generator is seeded from ``sampling.blend.seed`` and the batch's
    object ids, so every batch draws its own selection, reproducibly.

    Raises:
        ValueError: a prior is missing or unreadable, or belongs to another category than the objects
            its templated path was filled in for; the message names ``sampling.blend.prior_checkpoint``.
    """
    blend = cfg.sampling.blend
    device = batch.points.device
    templated = "{category}" in (blend.prior_checkpoint or "")
    loaded: dict[str, CategoryPrior] = {}
    priors: dict[str, CategoryPrior] = {}
    for category in sorted(set(batch.category)):
        path = prior_path(blend.prior_checkpoint or "", category)
        if str(path) not in loaded:
            loaded[str(path)] = load_prior(path, device, category)
        priors[category] = loaded[str(path)]
        if templated and priors[category].category != category:
            raise ValueError(
                f"sampling.blend.prior_checkpoint: {path} holds the prior of {priors[category].category!r}, "
                f"not of {category!r}"
            )
    # One 32-bit hash of both: torch's CPU generator keeps only a seed's low 32 bits.
    seed = zlib.crc32("\n".join([str(blend.seed), *batch.object_id]).encode())
    blend_generator = torch.Generator(device=device).manual_seed(seed)
    return blended_sample(
        diffusion,
        model_fn,
        _prior_x0_fn(priors, batch.category, diffusion, blend.prior_timestep),
        (len(batch), cfg.data.num_points, 3),
        generator=generator,
        blend_generator=blend_generator,
        milestones=blend.milestones,
        window_steps=blend.window_steps,
        select_prob=blend.select_prob,
        settings=SamplerSettings.from_config(cfg.diffusion),
        device=device,
        progress=progress,
    )
