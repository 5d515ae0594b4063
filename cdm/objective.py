"""The CDM training objective (paper Eq. 6): the diffusion term plus λ times the 3D prior constraint.

:func:`cdm_loss` draws the timestep and the noise, runs the network once and returns the terms as
:class:`LossTerms`; :func:`prior_3d_loss` is the constraint itself: renderings of a cloud and of the
ground truth from the H prior views (:func:`cdm.render.splat_points`) and their squared difference.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from cdm.cameras import Cameras
from cdm.config import PriorsConfig, RenderKind
from cdm.data.sample import Batch
from cdm.diffusion import GaussianDiffusion
from cdm.model import CDMNetwork
from cdm.registry import RENDER_KINDS
from cdm.render import splat_points

__all__ = ["LossTerms", "Prior3DLoss", "cdm_loss", "prior_3d_loss"]


class LossTerms(NamedTuple):
    """The loss of one batch and its two terms (scalars; ``total`` carries the gradient).

    Attributes:
        total: ``diffusion + λ·prior_3d`` (Eq. 6; λ = ``priors.lambda_3d``).
        diffusion: the diffusion term (Eq. 3 for ε-prediction; :meth:`GaussianDiffusion.loss`).
        prior_3d: the 3D prior constraint, 0 when ``priors.prior_3d`` is off or λ = 0.
    """

    total: Tensor
    diffusion: Tensor
    prior_3d: Tensor


class Prior3DLoss(NamedTuple):
    """Result of :func:`prior_3d_loss`.

    Attributes:
        loss: scalar, Eq. 6's prior term averaged over the batch.
        pred_images: ``(B, H, S, S)`` renderings of the compared cloud (with gradient).
        target_images: ``(B, H, S, S)`` renderings of the ground truth (no gradient); pass them back
            as ``target_images`` to skip re-rendering the same shape and views.
    """

    loss: Tensor
    pred_images: Tensor
    target_images: Tensor


def cdm_loss(
    *,
    network: CDMNetwork,
    diffusion: GaussianDiffusion,
    batch: Batch,
    priors: PriorsConfig,
    generator: torch.Generator,
    diverged: Callable[[str], Exception],
) -> LossTerms:
    """The loss of one batch (Eq. 6): draw t and ε, noise x₀, predict, and add λ × the 3D prior term.

    Args:
        network: the reconstruction network (image conditioning from ``batch``).
        diffusion: schedule and training target.
        batch: ``points`` ``(B, N, 3)`` ground truth x₀ (normalised world frame), images, cameras and
            the H prior-view cameras ``view_cameras`` ``(B, H)``.
        priors: the ``priors`` group (λ, H's renderings: size, point size, kind; compared cloud).
        generator: the only source of t and ε, on the batch's device.
        diverged: builds the error raised when the named quantity becomes NaN or infinite.
    Returns:
        :class:`LossTerms`.
    """
    x0 = batch.points
    device = generator.device
    t = torch.randint(0, diffusion.num_steps, (x0.shape[0],), generator=generator, device=device)
    noise = torch.randn(x0.shape, generator=generator, device=device)
    x_t = diffusion.q_sample(x0, t, noise)
    output = network(x_t, t, network.encode(batch), batch.camera)
    loss_diff = diffusion.loss(output, x0, noise, t)
    if not torch.isfinite(loss_diff):
        raise diverged("the diffusion loss")
    if not priors.prior_3d or priors.lambda_3d == 0.0:
        return LossTerms(loss_diff, loss_diff, torch.zeros((), device=device))
    # As written, Eq. 6 compares x_t with x₀: x_t does not depend on θ, so that term carries no
    # gradient. The default compares the network's clean estimate x̂₀ instead (see prior_3d_loss).
    cloud = diffusion.predict_x0(x_t, t, output) if priors.target == "x0_hat" else x_t
    if not torch.isfinite(cloud).all():
        raise diverged("the predicted clean cloud x̂₀")
    loss_prior = prior_3d_loss(cloud, x0, batch.view_cameras, priors.render_size, priors.point_size, priors.render_kind,
                               depth_layer=priors.depth_layer).loss
    return LossTerms(loss_diff + priors.lambda_3d * loss_prior, loss_diff, loss_prior)


def _validate_prior_inputs(pred_points: Tensor, gt_points: Tensor, view_cameras: Cameras) -> None:
    """:func:`prior_3d_loss`' clouds ``(B, N, 3)`` and ``(B, M, 3)`` and cameras ``(B, H)`` checked, each error
    naming the argument and the shape allowed."""
    if pred_points.ndim != 3 or gt_points.ndim != 3 or pred_points.shape[0] != gt_points.shape[0]:
        raise ValueError(
            f"pred_points and gt_points must be (B, N, 3) with the same B, got {tuple(pred_points.shape)} "
            f"and {tuple(gt_points.shape)}"
        )
    b = pred_points.shape[0]
    if len(view_cameras.batch_shape) != 2 or view_cameras.batch_shape[0] != b:
        raise ValueError(
            f"view_cameras must have batch shape (B, H) with B = {b}, got {tuple(view_cameras.batch_shape)}"
        )


def prior_3d_loss(
    pred_points: Tensor,
    gt_points: Tensor,
    view_cameras: Cameras,
    render_size: int,
    point_size: float,
    kind: RenderKind,
    target_images: Tensor | None = None,
    depth_layer: float | None = None,
) -> Prior3DLoss:
    """3D prior constraint (Eq. 6): ``Σ_{i=1..H} ‖proj(x, v_i) − proj(x₀, v_i)‖²``, batch mean.

    Each view's term is the mean squared pixel difference of the two S×S renderings, so the loss
    does not grow with the image size; views are summed as in Eq. 6.

    Which cloud ``x`` is compared is the caller's choice (``priors.target``). Eq. 6 writes the
    noised cloud ``x_t``, but ``x_t`` is made from ``x₀`` and noise, not by the network, so that term
    has no gradient and cannot train anything. The default therefore passes the predicted clean
    cloud ``x̂₀ = (x_t − √(1−ᾱ_t)·ε̂)/√ᾱ_t``, which depends on the network through ``ε̂``; ``x_t``
    stays selectable for the ablation (paper §3.2, Eq. 6; ``priors.target``).

    Args:
        pred_points: ``(B, N, 3)`` world coordinates of the compared cloud (x̂₀ or x_t).
        gt_points: ``(B, M, 3)`` world coordinates of the ground truth x₀.
        view_cameras: batch ``(B, H)``, the H prior views per sample.
        render_size: ``S`` in pixels (paper: 224).
        point_size: the point radius (``priors.point_size``) in NDC units, as PyTorch3D's
            point rasteriser (:func:`cdm.render.splat_points`).
        kind: ``"depth"`` (Co3D) or ``"planar"`` (ShapeNet) renderings (Fig. 3).
        target_images: optional cached ``(B, H, S, S)`` renderings of ``gt_points``.
        depth_layer: depth maps' front-layer thickness (``priors.depth_layer``); ignored for planar images.
    Returns:
        :class:`Prior3DLoss`.
    """
    _validate_prior_inputs(pred_points, gt_points, view_cameras)
    b, h = view_cameras.batch_shape
    s = render_size
    cameras = view_cameras.flatten()

    def render(points: Tensor) -> Tensor:
        layer = depth_layer if RENDER_KINDS[kind].depth else None
        return splat_points(points.repeat_interleave(h, 0), cameras, s, point_size, kind, layer).view(b, h, s, s)

    pred_images = render(pred_points)
    if target_images is None:
        with torch.no_grad():
            target_images = render(gt_points)
    elif target_images.shape != (b, h, s, s):
        raise ValueError(
            f"target_images must be (B, H, S, S) = {(b, h, s, s)}, got {tuple(target_images.shape)}; "
            "pass the target_images of an earlier call with the same views and render_size"
        )
    target_images = target_images.detach()
    per_view = (pred_images - target_images).pow(2).mean(dim=(-2, -1))  # (B, H)
    loss = per_view.sum(dim=1).mean()  # Eq. 6: sum over the H views
    return Prior3DLoss(loss=loss, pred_images=pred_images, target_images=target_images)
