"""The training loss (cdm.objective.cdm_loss, Eq. 6) on a case small enough to compute by hand.

A one-step schedule fixes t = 0 and ᾱ₀ = 1 − β₀, and a stand-in network outputs a learnt constant
cloud, so the diffusion term, x_t and x̂₀ are written out below; the rendering part of the prior term
is :func:`cdm.objective.prior_3d_loss`, checked against its own definition in ``tests/test_priors.py``.
"""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

from cdm.cameras import Cameras, look_at_cameras, orbit_cameras
from cdm.config import Prediction, PriorsConfig
from cdm.data.sample import Batch
from cdm.diffusion import GaussianDiffusion
from cdm.objective import cdm_loss, prior_3d_loss

# x₀, (B, N, 3) = (2, 4, 3) in the normalised world frame: two small tetrahedra around the origin.
X0 = torch.tensor(
    [
        [[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2], [-0.2, -0.2, -0.2]],
        [[0.3, 0.1, 0.0], [-0.1, 0.3, 0.0], [0.0, -0.1, 0.3], [0.1, 0.1, -0.3]],
    ]
)
SHIFT = torch.tensor([0.1, -0.2, 0.2])  # the stand-in's output is X0 + SHIFT: |SHIFT|² = 0.09


class _ConstantCloud(nn.Module):
    """Stand-in for :class:`cdm.model.CDMNetwork`: outputs its parameter ``cloud`` ``(B, N, 3)`` for
    every input and keeps the last ``x_t`` it saw, so the test can name the noise that was drawn."""

    def __init__(self, cloud: Tensor):
        super().__init__()
        self.cloud = nn.Parameter(cloud.clone())
        self.seen_x_t: Tensor | None = None

    def encode(self, batch: Batch) -> None:
        return None

    def forward(self, x_t: Tensor, t: Tensor, context: None, camera: Cameras) -> Tensor:
        assert t.tolist() == [0, 0]  # a one-step schedule has only t = 0
        self.seen_x_t = x_t.detach().clone()
        return self.cloud * 1.0


def _batch() -> Batch:
    b = X0.shape[0]
    elev, azim, dist = torch.tensor([20.0, -10.0]), torch.tensor([0.0, 60.0]), torch.tensor([1.5, 1.5])
    return Batch(
        image=torch.zeros(b, 3, 8, 8),
        mask=torch.ones(b, 1, 8, 8),
        depth=None,
        prior_2d=torch.zeros(b, 0, 8, 8),
        camera=look_at_cameras(elev, azim, dist),
        view_cameras=orbit_cameras(elev, azim, dist, 3),
        points=X0,
        category=("a", "a"),
        object_id=("0", "1"),
    )


def _loss(prediction: Prediction, beta0: float, priors: PriorsConfig):
    # num_steps = 1: the linear schedule is the single value β₀ = beta_start, so t = 0 and ᾱ₀ = 1 − β₀.
    diffusion = GaussianDiffusion(num_steps=1, beta_start=beta0, beta_end=beta0 + 0.1, prediction=prediction)
    network = _ConstantCloud(X0 + SHIFT)
    terms = cdm_loss(network=network, diffusion=diffusion, batch=_batch(), priors=priors,
                     generator=torch.Generator().manual_seed(0), diverged=RuntimeError)
    return terms, network


def _priors(**fields) -> PriorsConfig:
    return PriorsConfig(num_views=3, render_size=16, point_size=0.15, render_kind="planar", depth_layer=None, **fields)


def _prior(cloud: Tensor, priors: PriorsConfig) -> Tensor:
    return prior_3d_loss(cloud, X0, _batch().view_cameras, priors.render_size, priors.point_size,
                         priors.render_kind, depth_layer=priors.depth_layer).loss


def test_the_total_is_the_diffusion_term_plus_lambda_times_the_prior_on_x0_hat():
    priors = _priors(lambda_3d=2.5)
    # x₀-prediction with β₀ = 0: x_t = x₀ whatever the noise, the target is x₀ and x̂₀ is the output.
    terms, network = _loss("x0", 0.0, priors)
    torch.testing.assert_close(network.seen_x_t, X0)
    assert terms.diffusion.item() == pytest.approx(0.09 / 3)  # mean over B·N·3 of SHIFT² = |SHIFT|² / 3
    expected_prior = _prior(X0 + SHIFT, priors)
    assert expected_prior.item() > 1e-3  # a shifted cloud renders differently: the λ term is not 0
    torch.testing.assert_close(terms.prior_3d, expected_prior)
    torch.testing.assert_close(terms.total, terms.diffusion + 2.5 * expected_prior)
    (grad,) = torch.autograd.grad(terms.prior_3d, network.cloud)
    assert grad.abs().sum() > 0  # the x̂₀ target trains the network


def test_x0_hat_under_eps_prediction_inverts_the_forward_process():
    priors = _priors(lambda_3d=0.5)
    # β₀ = 0.36: √ᾱ₀ = 0.8, √(1 − ᾱ₀) = 0.6; x_t = 0.8·x₀ + 0.6·ε, so ε = (x_t − 0.8·x₀) / 0.6.
    terms, network = _loss("eps", 0.36, priors)
    noise = (network.seen_x_t - 0.8 * X0) / 0.6
    output = X0 + SHIFT
    torch.testing.assert_close(terms.diffusion, ((output - noise) ** 2).mean())  # Eq. 3
    x0_hat = (network.seen_x_t - 0.6 * output) / 0.8
    torch.testing.assert_close(terms.prior_3d, _prior(x0_hat, priors))
    torch.testing.assert_close(terms.total, terms.diffusion + 0.5 * terms.prior_3d)


def test_the_literal_x_t_target_compares_the_noised_cloud_and_carries_no_gradient():
    priors = _priors(lambda_3d=2.0, target="x_t_literal")
    terms, network = _loss("eps", 0.36, priors)
    torch.testing.assert_close(terms.prior_3d, _prior(network.seen_x_t, priors))
    assert not terms.prior_3d.requires_grad  # x_t is made from x₀ and ε, not by the network
    torch.testing.assert_close(terms.total, terms.diffusion + 2.0 * terms.prior_3d)
    # With β₀ = 0 the noised cloud is x₀ itself: the two renderings are equal and the term is exactly 0.
    exact, _ = _loss("x0", 0.0, priors)
    assert exact.prior_3d.item() == 0.0 and exact.total.item() == pytest.approx(0.09 / 3)


@pytest.mark.parametrize("fields", [{"lambda_3d": 0.0}, {"prior_3d": False, "lambda_3d": 2.5}])
def test_lambda_zero_or_no_prior_leaves_the_diffusion_term_alone(fields):
    terms, _ = _loss("x0", 0.0, _priors(**fields))
    assert terms.prior_3d.item() == 0.0
    assert terms.total.item() == terms.diffusion.item() == pytest.approx(0.09 / 3)
