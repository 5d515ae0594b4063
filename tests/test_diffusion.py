"""Schedule, target conversions and samplers of cdm.diffusion."""

import pytest
import torch

from cdm.config import DiffusionConfig
from cdm.diffusion import GaussianDiffusion, SamplerSettings


@pytest.mark.parametrize("prediction", ["eps", "x0", "v"])
def test_targets_round_trip_to_x0(prediction):
    d = GaussianDiffusion(1000, 1e-5, 8e-3, prediction)
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(4, 64, 3, generator=g, dtype=torch.float64) * 2 - 1
    noise = torch.randn(4, 64, 3, generator=g, dtype=torch.float64)
    t = torch.tensor([0, 10, 500, 999])
    x_t = d.q_sample(x0, t, noise)
    target = d.target(x0, noise, t)
    assert torch.allclose(d.predict_x0(x_t, t, target), x0, atol=1e-9)
    assert torch.allclose(d.eps_from_x0(x_t, t, x0), noise, atol=1e-6)


def test_forward_process_matches_closed_form_statistics():
    d = GaussianDiffusion(1000, 1e-5, 8e-3, "eps")
    a = d.alphas_cumprod
    assert a[0].item() == pytest.approx(1 - 1e-5)
    # ᾱ_T for a linear schedule: prod(1 - β), computed independently in log space.
    betas = torch.linspace(1e-5, 8e-3, 1000, dtype=torch.float64)
    assert a[-1].item() == pytest.approx(torch.exp(torch.log1p(-betas).sum()).item(), rel=1e-12)
    x0 = torch.full((1, 20000, 3), 0.5, dtype=torch.float64)
    t = torch.tensor([999])
    x_t = d.q_sample(x0, t, torch.randn(1, 20000, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    assert x_t.mean().item() == pytest.approx(0.5 * a[-1].sqrt().item(), abs=0.01)
    assert x_t.std().item() == pytest.approx((1 - a[-1]).sqrt().item(), abs=0.01)


def analytic_model(d: GaussianDiffusion, target_cloud: torch.Tensor):
    """The exact optimum when the data is one fixed cloud: x̂₀ is that cloud at every t."""

    def fn(x_t, t):
        eps = d.eps_from_x0(x_t, t, target_cloud.expand_as(x_t))
        return d.target(target_cloud.expand_as(x_t), eps, t)

    return fn


@pytest.mark.parametrize("prediction", ["eps", "x0", "v"])
@pytest.mark.parametrize(
    "sampler,steps,spacing", [("ddim", 20, "linspace"), ("ddim", 20, "trailing"), ("ddpm", 1000, "linspace")]
)
def test_samplers_recover_the_single_data_point(prediction, sampler, steps, spacing):
    d = GaussianDiffusion(1000, 1e-4, 2e-2, prediction)
    cloud = torch.rand(1, 32, 3, generator=torch.Generator().manual_seed(3)) * 1.6 - 0.8
    out = d.sample(analytic_model(d, cloud), (2, 32, 3), SamplerSettings(sampler, steps, clip_x0=None, spacing=spacing),
                   generator=torch.Generator().manual_seed(4))
    assert torch.allclose(out, cloud.expand(2, -1, -1), atol=1e-4)


def test_ddim_timestep_spacings():
    """``linspace`` spans T−1…0; ``trailing`` is diffusers' (``round(arange(T, 0, −T/n)) − 1``): it starts
    at T−1, steps by T/n and never asks the network about t = 0."""
    d = GaussianDiffusion(1000, 1e-5, 8e-3, "x0")
    assert d.timesteps(SamplerSettings("ddim", 25)) == [round(999 - 999 * i / 24) for i in range(25)]
    trailing = d.timesteps(SamplerSettings("ddim", 25, spacing="trailing"))
    assert trailing == list(range(999, 38, -40)) and trailing[-1] == 39
    assert d.timesteps(SamplerSettings("ddim", 3, spacing="trailing")) == [999, 666, 332]
    assert d.timesteps(SamplerSettings("ddim", 1000, spacing="trailing")) == list(range(999, -1, -1))
    assert d.timesteps(SamplerSettings("ddpm", 25, spacing="trailing")) == list(range(999, -1, -1))
    for n in range(1, 1001):  # 61 steps once drew 62 timesteps, the last t = −1
        grid = d.timesteps(SamplerSettings("ddim", n, spacing="trailing"))
        assert len(grid) == n and grid[0] == 999 and grid[-1] == round(1000 / n) - 1 >= 0, n


def test_ddim_is_deterministic_given_the_generator_and_clips():
    d = GaussianDiffusion(100, 1e-4, 2e-2, "x0")
    calls = []

    def wild(x_t, t):
        calls.append(int(t[0]))
        return torch.full_like(x_t, 5.0)

    a = d.sample(wild, (1, 8, 3), SamplerSettings("ddim", 10, clip_x0=1.0), generator=torch.Generator().manual_seed(0))
    b = d.sample(wild, (1, 8, 3), SamplerSettings("ddim", 10, clip_x0=1.0), generator=torch.Generator().manual_seed(0))
    assert torch.equal(a, b)
    assert torch.all(a == 1.0)  # the last DDIM step returns the clipped x̂₀
    assert calls[:10] == sorted(set(calls[:10]), reverse=True) and calls[0] == 99 and calls[9] == 0


def test_loss_is_zero_at_target_and_positive_elsewhere():
    d = GaussianDiffusion(1000, 1e-5, 8e-3, "v")
    x0, noise = torch.rand(2, 10, 3), torch.randn(2, 10, 3)
    t = torch.tensor([3, 900])
    assert d.loss(d.target(x0, noise, t), x0, noise, t).item() == pytest.approx(0.0, abs=1e-12)
    assert d.loss(torch.zeros_like(x0), x0, noise, t).item() > 0.1


def test_paper_profile_samples_with_pc2s_schedule_and_sampler():
    """PC²'s ``experiments/config/structured.py``: beta_start 1e-5, beta_end 8e-3, beta_schedule linear
    (1,000 training steps), diffusion_scheduler ddpm, num_inference_steps 1000; no x̂₀ clipping."""
    from pathlib import Path

    from sweeps.plan.spec import load_spec
    from sweeps.plan.trials import expand

    spec = Path(__file__).resolve().parent.parent / "sweeps" / "point_size.yaml"
    cfg = expand(load_spec(spec), "paper").cells[0].config
    assert (cfg.diffusion.sampler, cfg.diffusion.clip_x0, cfg.diffusion.prediction) == ("ddpm", None, "eps")
    d = GaussianDiffusion.from_config(cfg.diffusion)
    assert len(d.betas) == 1000 and d.betas[0].item() == 1e-5 and d.betas[-1].item() == pytest.approx(8e-3, rel=1e-15)
    steps = d.betas[1:] - d.betas[:-1]  # linear: every increment (8e-3 − 1e-5) / 999
    assert torch.allclose(steps, torch.full_like(steps, (8e-3 - 1e-5) / 999), rtol=1e-9, atol=0)
    assert torch.allclose(d.alphas_cumprod, torch.cumprod(1 - d.betas, 0))
    assert d.timesteps(SamplerSettings.from_config(cfg.diffusion)) == list(range(999, -1, -1))  # all 1,000 steps
    for profile in ("smoke", "local"):  # the small profiles keep the clipped DDIM they had
        small = expand(load_spec(spec), profile).cells[0].config.diffusion
        assert small.sampler == "ddim" and small.clip_x0 == 1.0


def test_defaults_are_the_configs():
    """The schedule and sampler defaults live in cdm.config alone: the classes' defaults are read from it."""
    cfg = DiffusionConfig()
    assert SamplerSettings() == SamplerSettings.from_config(cfg)
    plain, configured = GaussianDiffusion(), GaussianDiffusion.from_config(cfg)
    assert plain.prediction == configured.prediction and torch.equal(plain.betas, configured.betas)


def test_ddpm_with_fewer_steps_strides_as_diffusers_and_still_recovers_the_data_point():
    """``ddpm_steps`` = n takes diffusers' timesteps (multiples of T // n from 0) and the posterior across
    each stride; n = T is the full sampler, draw for draw."""
    d = GaussianDiffusion(1000, 1e-4, 2e-2, "eps")
    assert d.timesteps(SamplerSettings("ddpm", ddpm_steps=4)) == [750, 500, 250, 0]
    assert d.timesteps(SamplerSettings("ddpm", ddpm_steps=3)) == [666, 333, 0]
    assert (
        d.timesteps(SamplerSettings("ddpm", ddpm_steps=1000))
        == d.timesteps(SamplerSettings("ddpm"))
        == list(range(999, -1, -1))
    )
    cloud = torch.rand(1, 32, 3, generator=torch.Generator().manual_seed(3)) * 1.6 - 0.8
    model = analytic_model(d, cloud)

    def draw(**settings):
        return d.sample(
            model,
            (2, 32, 3),
            SamplerSettings("ddpm", clip_x0=None, **settings),
            generator=torch.Generator().manual_seed(4),
        )

    assert torch.equal(draw(ddpm_steps=1000), draw())
    assert torch.allclose(draw(ddpm_steps=10), cloud.expand(2, -1, -1), atol=1e-4)
    # Across a stride the step's variance is the posterior's of the pair, not β_t's: one noisy step from
    # t = 500 to 0 with x̂₀ exact lands on x₀, the last step adds no noise.
    assert torch.allclose(draw(ddpm_steps=2), cloud.expand(2, -1, -1), atol=1e-4)


def test_ddpm_steps_past_the_schedule_are_refused():
    with pytest.raises(ValueError, match="ddpm_steps must be <= diffusion.num_steps"):
        DiffusionConfig(num_steps=100, ddpm_steps=101)
