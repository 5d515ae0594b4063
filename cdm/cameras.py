"""Perspective cameras in PyTorch3D's conventions, so Co3D's cameras drop in unchanged.

Frames and axes (as PyTorch3D):
- world → view uses **row vectors**: ``X_view = X_world @ R + T``.
- view / NDC axes: +X points **left**, +Y **up**, +Z **into the screen** (away from the camera);
  a point in front of the camera has view depth ``z > 0``.
- NDC: ``x_ndc = f · X/Z + p_x``, ``y_ndc = f · Y/Z + p_y``; square images span [-1, 1] on both axes.
  Pixel (row i, column j) of an S×S image has its centre at
  ``x_ndc = 1 − (2j + 1)/S`` and ``y_ndc = 1 − (2i + 1)/S`` (column 0 is at +X, row 0 at +Y).

All camera tensors share a leading batch shape ``(*B)``; functions that take points expect
``(B, N, 3)`` points and cameras of batch shape ``(B,)`` (use :meth:`Cameras.flatten`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "Cameras",
    "look_at_cameras",
    "ndc_to_pixel",
    "orbit_cameras",
    "pixel_centers_ndc",
    "project_points",
    "select_sequence_views",
    "world_to_view",
]


@dataclass(frozen=True)
class Cameras:
    """A batch of pinhole cameras.

    Attributes:
        R: ``(*B, 3, 3)`` world→view rotation, row-vector convention.
        T: ``(*B, 3)`` world→view translation (world units).
        focal: ``(*B,)`` focal length in NDC units (``fx = fy``; 2 ↔ a 53° field of view).
        principal: ``(*B, 2)`` principal point in NDC (0 for a centred camera).
    """

    R: Tensor
    T: Tensor
    focal: Tensor
    principal: Tensor

    @property
    def batch_shape(self) -> torch.Size:
        return self.T.shape[:-1]

    def __len__(self) -> int:
        return self.T.shape[0]

    def __getitem__(self, index) -> Cameras:
        return Cameras(self.R[index], self.T[index], self.focal[index], self.principal[index])

    def to(self, device: torch.device | str) -> Cameras:
        return Cameras(self.R.to(device), self.T.to(device), self.focal.to(device), self.principal.to(device))

    def flatten(self) -> Cameras:
        """Merge all leading batch dims into one: ``(B, H)`` → ``(B·H,)``."""
        return Cameras(
            self.R.reshape(-1, 3, 3), self.T.reshape(-1, 3), self.focal.reshape(-1), self.principal.reshape(-1, 2)
        )

    @staticmethod
    def stack(cams: list[Cameras]) -> Cameras:
        """Stack cameras of equal batch shape along a new leading dim."""
        return Cameras(
            torch.stack([c.R for c in cams]),
            torch.stack([c.T for c in cams]),
            torch.stack([c.focal for c in cams]),
            torch.stack([c.principal for c in cams]),
        )

    def repeat_interleave(self, repeats: int) -> Cameras:
        """Repeat each camera ``repeats`` times along dim 0 (to pair cameras with H views)."""
        return Cameras(
            self.R.repeat_interleave(repeats, 0),
            self.T.repeat_interleave(repeats, 0),
            self.focal.repeat_interleave(repeats, 0),
            self.principal.repeat_interleave(repeats, 0),
        )


def world_to_view(points: Tensor, cameras: Cameras) -> Tensor:
    """``(B, N, 3)`` world points → ``(B, N, 3)`` view-frame points (+Z away from the camera)."""
    return points @ cameras.R + cameras.T[:, None, :]


def project_points(points: Tensor, cameras: Cameras, eps: float = 1e-6) -> Tensor:
    """Project world points to NDC.

    Args:
        points: ``(B, N, 3)`` world coordinates.
        cameras: batch ``(B,)``.
    Returns:
        ``(B, N, 3)``: NDC ``x`` (+left), NDC ``y`` (+up), and view depth ``z`` (world units).
        Points behind the camera (``z <= eps``) get their depth clamped for the division only.
    """
    view = world_to_view(points, cameras)
    z = view[..., 2]
    zc = z.clamp(min=eps)
    xy = cameras.focal[:, None, None] * view[..., :2] / zc[..., None] + cameras.principal[:, None, :]
    return torch.cat([xy, z[..., None]], dim=-1)


def ndc_to_pixel(xy_ndc: Tensor, image_size: int) -> Tensor:
    """NDC ``(..., 2)`` (x left, y up) → continuous pixel coords ``(..., 2)`` as (column, row).

    Pixel centres land on integers: NDC ``1 − 1/S`` ↦ column 0.
    """
    s = image_size
    col = (1.0 - xy_ndc[..., 0]) * s / 2.0 - 0.5
    row = (1.0 - xy_ndc[..., 1]) * s / 2.0 - 0.5
    return torch.stack([col, row], dim=-1)


def pixel_centers_ndc(image_size: int, device: torch.device | str | None = None) -> Tensor:
    """``(S, S, 2)`` NDC (x, y) of each pixel centre, indexed ``[row, column]``."""
    s = image_size
    coords = 1.0 - (2.0 * torch.arange(s, device=device, dtype=torch.float32) + 1.0) / s
    y, x = torch.meshgrid(coords, coords, indexing="ij")
    return torch.stack([x, y], dim=-1)


def look_at_cameras(elev_deg: Tensor, azim_deg: Tensor, dist: Tensor, focal: float | Tensor = 2.0) -> Cameras:
    """Cameras on a sphere around the origin, looking at it, world +Y up.

    ``azim = 0, elev = 0`` puts the camera on the world +Z axis; azimuth turns about +Y,
    elevation lifts the camera towards +Y (degrees). ``dist`` in world units.
    All inputs share one shape ``(*B,)``.
    """
    elev = torch.deg2rad(elev_deg.float())
    azim = torch.deg2rad(azim_deg.float())
    dist = dist.float()
    center = torch.stack(
        [dist * torch.cos(elev) * torch.sin(azim), dist * torch.sin(elev), dist * torch.cos(elev) * torch.cos(azim)],
        dim=-1,
    )
    z_axis = torch.nn.functional.normalize(-center, dim=-1)  # view +Z points at the origin
    up = torch.zeros_like(center)
    up[..., 1] = 1.0
    x_axis = torch.nn.functional.normalize(torch.cross(up, z_axis, dim=-1), dim=-1)
    y_axis = torch.cross(z_axis, x_axis, dim=-1)
    R = torch.stack([x_axis, y_axis, z_axis], dim=-1)  # columns are the view axes in world coords
    T = -(center[..., None, :] @ R)[..., 0, :]
    focal_t = torch.as_tensor(focal, dtype=torch.float32, device=dist.device).expand(dist.shape).clone()
    principal = torch.zeros(*dist.shape, 2, device=dist.device)
    return Cameras(R, T, focal_t, principal)


def orbit_cameras(
    elev_deg: Tensor, azim_deg: Tensor, dist: Tensor, num_views: int, focal: float | Tensor = 2.0
) -> Cameras:
    """H prior-view cameras evenly spaced in azimuth, starting at the input view (the H views of Eq. 6).

    The stand-in for "evenly spaced frames of the object's sequence" on data without a sequence.
    Inputs ``(B,)``; returns cameras of batch shape ``(B, H)``; view 0 is the input camera.
    """
    steps = torch.arange(num_views, dtype=torch.float32, device=azim_deg.device) * (360.0 / num_views)
    azim = azim_deg.float()[:, None] + steps[None, :]
    elev = elev_deg.float()[:, None].expand_as(azim)
    d = dist.float()[:, None].expand_as(azim)
    f = torch.as_tensor(focal, dtype=torch.float32, device=azim_deg.device)
    f = f[:, None].expand_as(azim) if f.ndim == 1 else f.expand_as(azim)
    return look_at_cameras(elev, azim, d, f)


def select_sequence_views(sequence_length: int, reference: int, num_views: int) -> list[int]:
    """Indices of H frames evenly spaced through an object's image sequence, starting at ``reference``.

    The paper's procedure for Co3D (§3.2): frames wrap around the sequence end.
    """
    if num_views < 1 or sequence_length < 1:
        raise ValueError("num_views and sequence_length must be >= 1")
    step = sequence_length / num_views
    return [(reference + math.floor(i * step)) % sequence_length for i in range(num_views)]
