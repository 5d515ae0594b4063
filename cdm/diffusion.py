"""Gaussian diffusion on point clouds: forward process, training targets and samplers.

Notation follows DDPM and the paper (Eq. 1–3): ``ᾱ_t = Π_{s≤t} (1 − β_s)`` and
``x_t = √ᾱ_t · x₀ + √(1 − ᾱ_t) · ε``. The network's raw output means one of three things
(``prediction``):

- ``eps``: ε̂, the paper's and PC²'s choice (Eq. 2–3);
- ``x0``: x̂₀ directly — learns far faster in short CPU budgets (``benchmarks/RESULTS.md``, "Which
  recipe learns": ε-prediction does not learn in 1,500 steps);
- ``v``: v̂ = √ᾱ_t · ε − √(1 − ᾱ_t) · x₀ (Salimans & Ho, 2022).

Whatever the target, the loss is the MSE to that target, and every sampler works from x̂₀, so the
3D prior constraint and x̂₀ clipping behave the same for all three.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from cdm.config import DiffusionConfig, Prediction, Sampler, Spacing
from cdm.registry import SAMPLERS

__all__ = ["GaussianDiffusion", "SamplerSettings"]

ModelFn = Callable[[Tensor, Tensor], Tensor]
"""``model_fn(x_t (B, N, 3), t (B,) long) -> raw network output (B, N, 3)``."""
_DEFAULT = DiffusionConfig()
"""The defaults' one home: the config's (PC²'s schedule, DDIM over 50 steps)."""


@dataclass(frozen=True)
class SamplerSettings:
    """How the reverse process runs: one value for :meth:`GaussianDiffusion.sample` and the BDM
    blended sampler (:func:`cdm.blend.blended_sample`), so the two cannot drift apart.

    Attributes:
        sampler: ``ddim`` (deterministic, η = 0, over ``steps`` evenly spaced timesteps) or ``ddpm``
            (ancestral, all T steps or ``ddpm_steps``; PC²'s sampler).
        steps: DDIM's number of steps; ignored by DDPM.
        clip_x0: clamp x̂₀ to ``[-clip_x0, clip_x0]`` at every step; ``None`` leaves it unclipped (PC²).
        spacing: where DDIM's steps sit (:meth:`GaussianDiffusion.timesteps`); ignored by DDPM.
        ddpm_steps: DDPM's number of steps; ``None`` = all T.
    """

    sampler: Sampler = _DEFAULT.sampler
    steps: int = _DEFAULT.sample_steps
    clip_x0: float | None = _DEFAULT.clip_x0
    spacing: Spacing = _DEFAULT.timestep_spacing
    ddpm_steps: int | None = _DEFAULT.ddpm_steps

    @classmethod
    def from_config(cls, cfg: DiffusionConfig) -> SamplerSettings:
        return cls(cfg.sampler, cfg.sample_steps, cfg.clip_x0, cfg.timestep_spacing, cfg.ddpm_steps)


class GaussianDiffusion:
    """Linear-β DDPM schedule (PC²: T = 1000, β from 1e-5 to 8e-3) with ε / x₀ / v targets.

    Args:
        num_steps: T.
        beta_start, beta_end: first and last β of the linear schedule.
        prediction: what the network output means (see module docstring).
    """

    def __init__(self, num_steps: int = _DEFAULT.num_steps, beta_start: float = _DEFAULT.beta_start,
                 beta_end: float = _DEFAULT.beta_end, prediction: Prediction = _DEFAULT.prediction):
        self.num_steps = num_steps
        self.prediction = prediction
        betas = torch.linspace(beta_start, beta_end, num_steps, dtype=torch.float64)
        alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)
        # Kept in float64 on the CPU; `_at` casts the few values a step needs.
        self.betas = betas
        self.alphas_cumprod = alphas_cumprod

    @classmethod
    def from_config(cls, cfg: DiffusionConfig) -> GaussianDiffusion:
        return cls(cfg.num_steps, cfg.beta_start, cfg.beta_end, cfg.prediction)

    def _at(self, values: Tensor, t: Tensor, like: Tensor) -> Tensor:
        """``values[t]`` shaped ``(B, 1, 1)`` in ``like``'s dtype and device."""
        return values[t.cpu()].to(device=like.device, dtype=like.dtype)[:, None, None]

    def q_sample(self, x0: Tensor, t: Tensor, noise: Tensor) -> Tensor:
        """Forward process: ``x_t = √ᾱ_t x₀ + √(1−ᾱ_t) ε``. Shapes ``(B, N, 3)``, ``t`` ``(B,)`` long."""
        a = self._at(self.alphas_cumprod, t, x0)
        return a.sqrt() * x0 + (1.0 - a).sqrt() * noise

    def target(self, x0: Tensor, noise: Tensor, t: Tensor) -> Tensor:
        """What the network is trained to output for ``(x₀, ε, t)``."""
        if self.prediction == "eps":
            return noise
        if self.prediction == "x0":
            return x0
        a = self._at(self.alphas_cumprod, t, x0)
        return a.sqrt() * noise - (1.0 - a).sqrt() * x0

    def predict_x0(self, x_t: Tensor, t: Tensor, output: Tensor) -> Tensor:
        """x̂₀ from the network output (the inverse of the forward process for each target)."""
        if self.prediction == "x0":
            return output
        a = self._at(self.alphas_cumprod, t, x_t)
        if self.prediction == "eps":
            return (x_t - (1.0 - a).sqrt() * output) / a.sqrt()
        return a.sqrt() * x_t - (1.0 - a).sqrt() * output

    def eps_from_x0(self, x_t: Tensor, t: Tensor, x0: Tensor) -> Tensor:
        """ε implied by ``x_t`` and a (possibly clipped) x̂₀."""
        a = self._at(self.alphas_cumprod, t, x_t)
        return (x_t - a.sqrt() * x0) / (1.0 - a).sqrt()

    def loss(self, output: Tensor, x0: Tensor, noise: Tensor, t: Tensor) -> Tensor:
        """Diffusion loss, MSE to the target (Eq. 3 for ``eps``); a scalar."""
        return torch.mean((output - self.target(x0, noise, t)) ** 2)

    def sample(
        self,
        model_fn: ModelFn,
        shape: tuple[int, int, int],
        settings: SamplerSettings = SamplerSettings(),
        *,
        generator: torch.Generator | None = None,
        device: torch.device | str = "cpu",
        progress: Callable[[int, int], None] | None = None,
    ) -> Tensor:
        """Draw ``(B, N, 3)`` clouds by reverse diffusion from ``x_T ~ N(0, I)`` (see :class:`SamplerSettings`).

        Clipping x̂₀ keeps short-trained models from diverging (unclipped 100-step DDIM after minutes of
        CPU training gave diverged clouds). Noise comes from ``generator`` only.
        """
        x = torch.randn(shape, generator=generator, device=device)
        timesteps = self.timesteps(settings)
        for i, t_int in enumerate(timesteps):
            t = torch.full((shape[0],), t_int, dtype=torch.long, device=device)
            x = self.step(x, t, i, timesteps, self.predict_x0(x, t, model_fn(x, t)), settings, generator)
            if progress is not None:
                progress(i + 1, len(timesteps))
        return x

    def step(
        self,
        x_t: Tensor,
        t: Tensor,
        i: int,
        timesteps: list[int],
        x0_hat: Tensor,
        settings: SamplerSettings,
        generator: torch.Generator | None,
    ) -> Tensor:
        """One reverse step from ``timesteps[i]`` (``t``, per sample) to the next, given the clean estimate.

        Clamps ``x0_hat`` to ``[-clip_x0, clip_x0]`` first, then takes the DDIM (η = 0) or DDPM step;
        ``generator`` feeds the DDPM noise. Shared by :meth:`sample` and the BDM blended sampler.
        """
        if settings.clip_x0 is not None:
            x0_hat = x0_hat.clamp(-settings.clip_x0, settings.clip_x0)
        t_next = timesteps[i + 1] if i + 1 < len(timesteps) else -1
        if SAMPLERS[settings.sampler].ancestral:
            return self._ddpm_step(x_t, timesteps[i], t_next, x0_hat, generator)
        return self._ddim_step(x_t, t, x0_hat, t_next)

    def timesteps(self, settings: SamplerSettings) -> list[int]:
        """The sampler's timesteps, noisiest first. ``ddpm``: all T, or with ``ddpm_steps`` = n the
        multiples of T // n below n · (T // n) (diffusers' ``DDPMScheduler.set_timesteps``). ``ddim``:
        ``steps`` of them evenly spaced by ``settings.spacing``:

        - ``linspace``: from T−1 down to 0, both included, so the last x̂₀ is predicted at t = 0;
        - ``trailing``: T−1, T−1−T/steps, …, T/steps − 1 (Lin et al., 2024, "Common Diffusion Noise
          Schedules and Sample Steps are Flawed"; diffusers' ``timestep_spacing="trailing"``),
          so the last x̂₀ is predicted at t = T/steps − 1. An x₀-predicting network must rebuild its
          input at t = 0 through all its layers and does it worse than it denoises a little noise:
          on the local profile's point size 0.04 cell (1,800 steps), 25 DDIM steps scored CD×1000
          63.2 with ``linspace`` and 59.9 with t = 0 left out (``benchmarks/RESULTS.md``).
        """
        if SAMPLERS[settings.sampler].ancestral:
            n = settings.ddpm_steps or self.num_steps
            return [i * (self.num_steps // n) for i in range(n)][::-1]
        if settings.spacing == "trailing":
            # T − i·T/n for i < n, not arange(T, 0, −T/n): its float step can add an n+1-th value ≈ 0 (t = −1).
            stride = self.num_steps / settings.steps
            grid = (
                (self.num_steps - torch.arange(settings.steps, dtype=torch.float64) * stride).round().long() - 1
            ).tolist()
        else:
            grid = torch.linspace(self.num_steps - 1, 0, settings.steps).round().long().tolist()
        return sorted(set(grid), reverse=True)

    def _ddim_step(self, x_t: Tensor, t: Tensor, x0_hat: Tensor, t_prev: int) -> Tensor:
        if t_prev < 0:
            return x0_hat
        eps = self.eps_from_x0(x_t, t, x0_hat)
        a_prev = self.alphas_cumprod[t_prev].to(dtype=x_t.dtype, device=x_t.device)
        return a_prev.sqrt() * x0_hat + (1.0 - a_prev).sqrt() * eps

    def _ddpm_step(self, x_t: Tensor, t: int, t_prev: int, x0_hat: Tensor, generator: torch.Generator | None) -> Tensor:
        """Ancestral step with the posterior q(x_{t_prev} | x_t, x̂₀) (DDPM Eq. 6–7; ``t_prev`` = −1 ends at x₀).
        Between consecutive timesteps β is the schedule's β_t; across a stride, 1 − ᾱ_t / ᾱ_prev."""
        a_t = self.alphas_cumprod[t]
        a_prev = self.alphas_cumprod[t_prev] if t_prev >= 0 else torch.tensor(1.0, dtype=torch.float64)
        beta = self.betas[t] if t_prev == t - 1 else 1.0 - a_t / a_prev
        coef_x0 = (a_prev.sqrt() * beta / (1.0 - a_t)).item()
        coef_xt = ((1.0 - beta).sqrt() * (1.0 - a_prev) / (1.0 - a_t)).item()
        mean = coef_x0 * x0_hat + coef_xt * x_t
        if t_prev < 0:
            return mean
        var = (beta * (1.0 - a_prev) / (1.0 - a_t)).item()
        noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
        return mean + var**0.5 * noise
