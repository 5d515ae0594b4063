"""BDM blending (cdm.blend) and the category prior it blends with (cdm.prior_model)."""

from __future__ import annotations

import dataclasses
import math
import os
import re
import shutil
from pathlib import Path

import pytest
import torch

from cdm.__main__ import main
from cdm.blend import _prior_x0_fn, blend_windows, blended_sample, matched_timesteps, prior_timesteps
from cdm.checkpoint import CHECKPOINT_FILE, load_checkpoint, save_checkpoint
from cdm.config import load_config
from cdm.data import build_dataset
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.data.sample import collate
from cdm.diffusion import GaussianDiffusion, SamplerSettings
from cdm.evaluate import reconstruct
from cdm.model import CDMNetwork
from cdm.prior_model import (
    PRIOR_KIND,
    CategoryPrior,
    ensure_priors,
    load_prior,
    prior_config,
    train_prior,
)
from tests.conftest import TINY, tiny_config

BDM_MILESTONES = (936, 872, 128, 64, 32)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _recon_eps(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """A stand-in reconstruction model: depends on x_t and t, so any change of either shows."""
    return 0.5 * x + 1e-3 * t[:, None, None].float()


def _prior_x0(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    return -0.3 * x + 0.1


def _blend(
    diffusion, model_fn, prior_x0, sampler, steps, select_prob, milestones=BDM_MILESTONES, window=16, shape=(2, 64, 3)
):
    return blended_sample(
        diffusion, model_fn, prior_x0, shape, generator=_gen(0), blend_generator=_gen(1), milestones=milestones,
        window_steps=window, select_prob=select_prob, settings=SamplerSettings(sampler, steps),
    )


@pytest.mark.parametrize("sampler,steps", [("ddim", 50), ("ddpm", 1000)])
def test_select_prob_zero_is_exactly_the_plain_sampler(sampler, steps):
    diffusion = GaussianDiffusion(prediction="eps")
    plain = diffusion.sample(_recon_eps, (2, 64, 3), SamplerSettings(sampler, steps), generator=_gen(0))
    blended = _blend(diffusion, _recon_eps, _prior_x0, sampler, steps, select_prob=0.0)
    assert torch.equal(blended.points, plain)
    assert len(blended.from_prior) == 5 and not any(m.any() for m in blended.from_prior)
    # A coin that can land on the prior does change the result: the windows really ran.
    assert not torch.equal(_blend(diffusion, _recon_eps, _prior_x0, sampler, steps, select_prob=0.5).points, plain)


def test_select_prob_one_follows_the_prior_trajectory_inside_windows():
    """DDIM is deterministic: with p = 1 the result is the plain sampler run with the prior's x̂₀ at
    exactly the window steps and the reconstruction model's everywhere else."""
    diffusion = GaussianDiffusion(prediction="x0")
    timesteps = diffusion.timesteps(SamplerSettings("ddim", 50))
    in_window = {timesteps[i] for w in blend_windows(timesteps, BDM_MILESTONES, 16) for i in w}
    assert len(in_window) == 9  # 938, 877, 856, 143, 122, 82, 61, 41, 20

    def recon_x0(x, t):
        return 0.8 * x

    def switched(x, t):
        return _prior_x0(x, t) if int(t[0]) in in_window else recon_x0(x, t)

    reference = diffusion.sample(switched, (2, 64, 3), SamplerSettings("ddim", 50), generator=_gen(0))
    blended = _blend(diffusion, recon_x0, _prior_x0, "ddim", 50, select_prob=1.0)
    assert torch.equal(blended.points, reference)
    assert all(m.all() for m in blended.from_prior)
    assert not torch.equal(
        reference, diffusion.sample(recon_x0, (2, 64, 3), SamplerSettings("ddim", 50), generator=_gen(0))
    )


@pytest.mark.parametrize("sampler,steps", [("ddim", 50), ("ddpm", 1000)])
def test_points_of_a_final_window_come_from_the_branch_the_coin_picked(sampler, steps):
    """Constant clean estimates (+0.25 reconstruction, −0.25 prior) and a last window ending at x₀:
    every final point is one branch's exactly, and the mask says which."""
    diffusion = GaussianDiffusion(prediction="x0")

    def recon(x, t):
        return torch.full_like(x, 0.25)

    def prior(x, t):
        return torch.full_like(x, -0.25)

    every = _blend(diffusion, recon, prior, sampler, steps, select_prob=1.0, milestones=(16,))
    torch.testing.assert_close(every.points, torch.full((2, 64, 3), -0.25))
    half = _blend(diffusion, recon, prior, sampler, steps, select_prob=0.5, milestones=(16,), shape=(4, 1000, 3))
    (mask,) = half.from_prior
    torch.testing.assert_close(half.points, torch.where(mask[..., None], -0.25, 0.25).expand(4, 1000, 3))


def test_fraction_taken_from_the_prior_is_select_prob():
    diffusion = GaussianDiffusion(prediction="eps")
    result = _blend(diffusion, _recon_eps, _prior_x0, "ddim", 50, select_prob=0.5, shape=(4, 1000, 3))
    bound = 4 * math.sqrt(0.25 / 4000)  # 4 σ of a binomial share over 4,000 points: ±0.032
    shares = [m.float().mean().item() for m in result.from_prior]
    assert len(shares) == 5 and all(abs(s - 0.5) < bound for s in shares), shares
    # Windows draw independent coins: two masks agree on about half the points, not on all.
    assert abs((result.from_prior[0] == result.from_prior[1]).float().mean().item() - 0.5) < bound


def test_windows_cover_window_steps_timesteps():
    diffusion = GaussianDiffusion()
    ddpm = diffusion.timesteps(SamplerSettings("ddpm", 0))
    windows = blend_windows(ddpm, BDM_MILESTONES, 16)
    # BDM numbering: milestone 936 runs x_936 → x_920, our steps t = 935 … 920.
    assert [(ddpm[w[0]], ddpm[w[-1]], len(w)) for w in windows] == [
        (935, 920, 16), (871, 856, 16), (127, 112, 16), (63, 48, 16), (31, 16, 16)]
    ddim = diffusion.timesteps(SamplerSettings("ddim", 50))
    for m, w in zip(BDM_MILESTONES, blend_windows(ddim, BDM_MILESTONES, 16)):
        covered = {s for i in w for s in range(ddim[i + 1] + 1 if i + 1 < len(ddim) else 0, ddim[i] + 1)}
        assert set(range(m - 16, m)) <= covered and len(w) <= 2
    # Five DDIM steps: 936 and 872 share the first step, 128/64/32 the fourth; each step blends once.
    assert blend_windows(diffusion.timesteps(SamplerSettings("ddim", 5)), BDM_MILESTONES, 16) == [(0,), (3,)]


def test_prior_noise_level_matches_the_reconstruction_schedule():
    pc2 = GaussianDiffusion()
    assert torch.equal(matched_timesteps(pc2.alphas_cumprod, pc2.alphas_cumprod), torch.arange(1000))
    bdm = GaussianDiffusion(1000, 1e-4, 2e-2)
    matched = matched_timesteps(pc2.alphas_cumprod, bdm.alphas_cumprod)
    assert matched[[10, 100, 500, 999]].tolist() == [3, 59, 312, 628]
    ratio = pc2.alphas_cumprod / bdm.alphas_cumprod[matched]
    assert 0.99 < ratio.min() and ratio.max() < 1.01  # the same x_t scale within 1 %
    assert (matched.diff() >= 0).all()


def test_the_prior_sees_bdms_timestep_index_by_default():
    pc2, bdm = GaussianDiffusion(), GaussianDiffusion(1000, 1e-4, 2e-2)
    assert load_config().sampling.blend.prior_timestep == "same_index"
    assert torch.equal(prior_timesteps(pc2.alphas_cumprod, bdm.alphas_cumprod, "same_index"), torch.arange(1000))
    assert torch.equal(prior_timesteps(pc2.alphas_cumprod, bdm.alphas_cumprod, "log_snr"),
                       matched_timesteps(pc2.alphas_cumprod, bdm.alphas_cumprod))
    with pytest.raises(
        ValueError, match="sampling.blend.prior_timestep: same_index needs a prior of 1000 timesteps, this one has 500"
    ):
        prior_timesteps(pc2.alphas_cumprod, GaussianDiffusion(500).alphas_cumprod, "same_index")
    seen = []

    def network(x, t):  # the prior's ε-network: records the timesteps it is called at
        seen.append(t.tolist())
        return torch.zeros_like(x)

    t = torch.tensor([500, 64, 500])
    for mode, want in (
        ("same_index", [[500, 500], [64]]),
        ("log_snr", [[312, 312], [matched_timesteps(pc2.alphas_cumprod, bdm.alphas_cumprod)[64].item()]]),
    ):
        seen.clear()
        priors = {"chair": CategoryPrior(network, bdm, "chair"), "lamp": CategoryPrior(network, bdm, "lamp")}
        _prior_x0_fn(priors, ["chair", "lamp", "chair"], pc2, mode)(torch.randn(3, 8, 3), t)
        assert seen == want, mode


@pytest.mark.parametrize(
    "value,message",
    [("[1200, 64]", r"sampling\.blend\.milestones: \[1200\] outside the schedule"),
     ("[936, 8]", r"sampling\.blend\.milestones: \[8\] outside the schedule"),
     ("[64, 56]", r"sampling\.blend\.milestones: windows of 16 steps starting at 64 and 56 overlap")],
)
def test_cli_rejects_milestones_outside_the_schedule(tmp_path, capsys, value, message):
    out = tmp_path / "run"
    argv = ["train", "--set", "sampling.blend.enabled=true", "--set", "sampling.blend.prior_checkpoint=p",
            "--set", f"sampling.blend.milestones={value}", "--set", f"train.out_dir={out}"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1
    assert re.search(message, err), err
    assert not out.exists()


def test_sweep_spec_with_bad_milestones_exits_2_before_ray(tmp_path, capsys):
    from sweeps import run

    spec = tmp_path / "bad.yaml"
    spec.write_text("name: bad\nbase: {sampling.blend.enabled: true, sampling.blend.prior_checkpoint: auto, "
                    "sampling.blend.milestones: [1001]}\ngrid: {priors.prior_3d: [false, true]}\n")
    assert run.main([str(spec), "--smoke", "--dry-run"]) == 2
    assert "sampling.blend.milestones: [1001] outside the schedule" in capsys.readouterr().err


def _tiny_prior_overrides(steps: int = 6) -> dict:
    return {"train.steps": steps, "train.log_every": 3}


@pytest.fixture(scope="module")
def priors(tmp_path_factory):
    """Tiny chair and mug priors (6 steps each) under one folder, named ``<category>``."""
    root = tmp_path_factory.mktemp("priors")
    cfg = load_config(TINY, _tiny_prior_overrides())
    for category in ("chair", "mug"):
        train_prior(prior_config(cfg, category), root / category)
    return root


def test_train_prior_cli_defaults_to_bdm_schedule_and_keeps_explicit_fields(tmp_path, capsys):
    sets = [f"{k}={v}" for k, v in {"data.num_points": 128, "data.train_objects": 4, "data.image_size": 32,
                                      "model.widths": "[16,16]", "model.voxel_resolutions": "[8,4]",
                                      "model.time_embed_dim": 16, "train.steps": 4, "train.log_every": 2}.items()]
    argv = ["train-prior", "--category", "sofa", "--out", str(tmp_path / "sofa")]
    assert main(argv + [a for s in sets for a in ("--set", s)]) == 0
    state = load_checkpoint(tmp_path / "sofa")
    assert state.kind == PRIOR_KIND and state.category == "sofa" and state.step == 4
    d = state.config["diffusion"]
    assert (d["beta_start"], d["beta_end"], d["num_steps"], d["prediction"]) == (1e-4, 2e-2, 1000, "eps")
    assert "step 4: loss" in capsys.readouterr().out
    assert main(argv + ["--set", "diffusion.beta_end=0.01", "--set", "diffusion.prediction=x0"]
                + [a for s in sets for a in ("--set", s)]) == 0
    d = load_checkpoint(tmp_path / "sofa").config["diffusion"]
    assert (d["beta_start"], d["beta_end"], d["prediction"]) == (1e-4, 0.01, "x0")
    assert main(["train-prior", "--category", "car", "--out", str(tmp_path / "car")]) == 2
    assert "data.categories: ['car'] not in the procedural data set" in capsys.readouterr().err
    assert not (tmp_path / "car").exists()


def test_prior_training_lowers_its_loss(tmp_path):
    cfg = prior_config(load_config(TINY, {"train.steps": 60, "train.log_every": 10}), "mug")
    losses = []
    train_prior(cfg, tmp_path / "mug", progress=lambda step, loss: losses.append(loss))
    assert len(losses) == 6 and losses[-1] < 0.7 * losses[0], losses


def test_load_prior_refuses_a_cdm_checkpoint(tmp_path, priors):
    state = load_checkpoint(priors / "chair")
    save_checkpoint(dataclasses.replace(state, kind=None), tmp_path)
    with pytest.raises(ValueError, match=r"sampling\.blend\.prior_checkpoint: .* is not a category prior"):
        load_prior(tmp_path)
    with pytest.raises(ValueError, match=r"sampling\.blend\.prior_checkpoint: checkpoint: .* does not exist"):
        load_prior(tmp_path / "missing")
    assert load_prior(priors / "mug").category == "mug"


def _batch_and_network(tmp_path):
    cfg = tiny_config(tmp_path)
    val = build_dataset(cfg, "val")
    batch = collate([val[0], val[1]])  # one chair, one mug
    torch.manual_seed(0)
    network = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d]).eval()
    return cfg, batch, network


def test_reconstruct_blends_with_each_objects_category_prior(tmp_path, priors):
    cfg, batch, network = _batch_and_network(tmp_path)
    assert sorted(batch.category) == ["chair", "mug"]
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)
    plain = reconstruct(network, diffusion, batch, cfg, _gen(5))

    def blended(**blend):
        sets = {"sampling.blend.enabled": True, "sampling.blend.prior_checkpoint": str(priors / "{category}"),
                "sampling.blend.milestones": [936, 128], **{f"sampling.blend.{k}": v for k, v in blend.items()}}
        return reconstruct(network, diffusion, batch, load_config(cfg.to_dict(), sets), _gen(5))

    assert torch.equal(blended(select_prob=0.0), plain)
    mixed = blended(select_prob=0.5)
    assert not torch.equal(mixed, plain) and torch.equal(mixed, blended(select_prob=0.5))
    assert not torch.equal(mixed, blended(select_prob=0.5, seed=1))
    wrong = tmp_path / "wrong"
    for category in ("chair", "mug"):  # both folders hold the chair prior
        shutil.copytree(priors / "chair", wrong / category)
    with pytest.raises(ValueError, match=r"holds the prior of 'chair', not of 'mug'"):
        reconstruct(network, diffusion, batch, load_config(cfg.to_dict(), {
            "sampling.blend.enabled": True, "sampling.blend.prior_checkpoint": str(wrong / "{category}")}), _gen(5))
    with pytest.raises(ValueError, match=r"'auto' is resolved inside sweep trials"):
        reconstruct(network, diffusion, batch, load_config(cfg.to_dict(), {
            "sampling.blend.enabled": True, "sampling.blend.prior_checkpoint": "auto"}), _gen(5))


def test_ensure_priors_trains_each_category_once_and_shares_across_cells(tmp_path):
    lines: list[str] = []
    cfg = load_config(TINY, {**_tiny_prior_overrides(4), "sampling.blend.enabled": True,
                             "sampling.blend.prior_checkpoint": "auto"})
    disabled = load_config(cfg.to_dict(), {"sampling.blend.enabled": False})
    assert ensure_priors(disabled, tmp_path / "cache") is disabled and not (tmp_path / "cache").exists()
    resolved = ensure_priors(cfg, tmp_path / "cache", lines.append)
    template = Path(resolved.sampling.blend.prior_checkpoint)
    assert template.parent == tmp_path / "cache" and template.name.startswith("{category}-") and len(lines) == 2
    files = {c: Path(str(template).replace("{category}", c)) / CHECKPOINT_FILE for c in ("chair", "mug")}
    stamps = {c: os.stat(f).st_mtime_ns for c, f in files.items()}
    # The PC² cell (2D and 3D priors off) of the same sweep reuses them: priors do not change the clouds.
    other = load_config(cfg.to_dict(), {"priors.prior_3d": False, "priors.prior_2d": "none"})
    assert ensure_priors(other, tmp_path / "cache", lines.append).sampling.blend.prior_checkpoint == str(template)
    assert {c: os.stat(f).st_mtime_ns for c, f in files.items()} == stamps and "reusing" in lines[-1]
    assert load_prior(files["mug"].parent).diffusion.betas[-1].item() == pytest.approx(2e-2)
    # A different training budget is another prior.
    longer = load_config(cfg.to_dict(), {"train.steps": 5})
    assert ensure_priors(longer, tmp_path / "cache").sampling.blend.prior_checkpoint != str(template)
