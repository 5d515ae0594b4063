"""Cost of BDM blending at sampling time: reconstruction with blending ÷ without (issue 9).

Inside a window both the reconstruction model and the category prior take every step, elsewhere the
reconstruction model alone, so sampling should cost about

    1 + window share × (prior call ÷ CDM call),   window share = window steps ÷ all steps

if every step cost the same: the prior is the same denoiser without the image conditioning. On a
CPU the sparse voxel branch costs more for spread-out clouds (high noise) than for surfaces, so
windows at high noise weigh a little more than their share.

Rows: one prior call ÷ one CDM network call on the same x_t; whole samplings with ÷ without blending
on DDIM 25 steps, at ``select_prob`` 0 (the trajectory stays the plain one: the cost of the windows
alone) and 0.5 (BDM's), and without ``--quick`` the 1000-step DDPM BDM samples with. Quick config
(64², N=512, widths 32/64/128, sparse voxels), B=4, one thread, an untrained CDM network and a
one-step prior (weights do not change a call's cost, though they steer the trajectory), BDM's
milestones (936, 872, 128, 64, 32) and 16-step windows.
"""

from __future__ import annotations

from pathlib import Path

import torch

from benchmarks.common import paired
from cdm.blend import blend_windows
from cdm.config import Config, load_config
from cdm.data import build_dataset
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.data.sample import collate
from cdm.diffusion import GaussianDiffusion, SamplerSettings
from cdm.evaluate import reconstruct
from cdm.model import CDMNetwork
from cdm.prior_model import load_prior, prior_config, train_prior

__all__ = ["blend_overhead"]

QUICK = Path(__file__).resolve().parents[1] / "configs" / "quick.yaml"
BATCH = 4


def _sampler(cfg: Config, network: CDMNetwork, batch):
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)
    return lambda: reconstruct(network, diffusion, batch, cfg, torch.Generator().manual_seed(0))


def blend_overhead(quick: bool, out_dir: str) -> list[dict]:
    # The prior trains on the CPU too: on a GPU machine it would resolve to the dense voxel back-end,
    # which it keeps when sampled, and dense is several times slower on a CPU thread than sparse.
    base = load_config(
        QUICK, {"data.categories": ["chair"], "train.threads": 1, "train.device": "cpu", "train.out_dir": out_dir}
    )
    prior_dir = train_prior(
        prior_config(load_config(base.to_dict(), {"train.steps": 1}), "chair"), Path(out_dir) / "prior_chair"
    ).checkpoint
    batch = collate([build_dataset(base, "val")[i] for i in range(BATCH)])
    torch.manual_seed(0)
    network = CDMNetwork(base.model, PRIOR_2D_CHANNELS[base.priors.prior_2d], device="cpu").eval()

    prior = load_prior(prior_dir)
    t = torch.full((BATCH,), 500, dtype=torch.long)
    x_t = GaussianDiffusion.from_config(base.diffusion).q_sample(
        batch.points, t, torch.randn(batch.points.shape, generator=torch.Generator().manual_seed(0)))
    with torch.no_grad():
        context = network.encode(batch)
        calls = paired(
            lambda: network(x_t, t, context, batch.camera), lambda: prior.network(x_t, t), repeats=10 if quick else 30
        )
    rows = [
        {
            "benchmark": "BDM blending: one prior call ÷ one CDM call",
            "case": f"same x_t (t=500), B={BATCH}, N={base.data.num_points}",
            "without_s": calls.a_s,
            "with_s": calls.b_s,
            "ratio": calls.ratio,
            "target": "<= 1 (no image conditioning)",
        }
    ]

    ddim = {"diffusion.sampler": "ddim", "diffusion.sample_steps": 25}
    cases = [(ddim, 0.0, 6 if quick else 10), (ddim, 0.5, 6 if quick else 10)]
    cases += [] if quick else [({"diffusion.sampler": "ddpm"}, 0.5, 2)]
    for sets, select_prob, repeats in cases:
        plain = load_config(base.to_dict(), sets)
        blended = load_config(
            plain.to_dict(),
            {
                "sampling.blend.enabled": True,
                "sampling.blend.prior_checkpoint": str(prior_dir),
                "sampling.blend.select_prob": select_prob,
            },
        )
        d, b = plain.diffusion, blended.sampling.blend
        timesteps = GaussianDiffusion.from_config(d).timesteps(SamplerSettings.from_config(d))
        share = sum(len(w) for w in blend_windows(timesteps, b.milestones, b.window_steps)) / len(timesteps)
        result = paired(_sampler(plain, network, batch), _sampler(blended, network, batch), repeats=repeats)
        rows.append({"benchmark": "BDM blending: sampling with ÷ without",
                     "case": f"{d.sampler.upper()} {len(timesteps)} steps, select_prob {select_prob:g}, B={BATCH}, "
                             f"N={plain.data.num_points}, window share {share:.3f}",
                     "without_s": result.a_s, "with_s": result.b_s, "ratio": result.ratio,
                     "target": f"≈ {1 + share:.3f} (1 + window share)"})
    return rows
