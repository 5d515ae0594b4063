"""kornia and OpenCV against the project's own geometry and image operations (issue 59, section 5).

    python benchmarks/run.py --only kornia_ops [--quick]

Each row times two ways of one operation alternately in one process (``a`` ours or the former code,
``b`` the library's; ``ratio`` = median of per-pair ``b / a``, so > 1 means the library is slower),
one torch thread and one OpenCV thread, and states the largest difference of their values:

- the mask distance transform of the conditioning map (B = 8 masks): the pure-torch ``O(S³)`` passes
  (:func:`cdm.model.conditioning.mask_distance_transform`) against OpenCV's precise L2 transform
  (:func:`opencv_distance_transform`, as PC² computes it; not adopted); kornia's
  ``contrib.distance_transform`` (iterated convolutions) against OpenCV's;
- camera projection (``cdm.cameras.project_points``, forward + backward) against kornia's
  ``transform_points`` + ``camera.project_points`` with the same cameras as 4×4 and 3×3 matrices;
- the splat's footprint filter (``cdm.render._filter_and_crop``, forward + backward) against kornia's
  ``filter2d`` (a depthwise ``conv2d``) with the full footprint table, valid padding;
- the front layer's window minimum: the former ``-max_pool2d(-z)`` against kornia's ``erosion``, now
  ``cdm.render._window_min``;
- the contour prior: OpenCV's Canny per image (``cdm.data.priors2d.contour_map``) against kornia's
  ``filters.canny`` on the batch (a different detector: its share of pixels that differ is the
  "difference").
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import kornia
import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry import camera as kcamera
from kornia.geometry import transform_points
from torch import Tensor

from benchmarks.common import paired
from cdm.cameras import Cameras, orbit_cameras, project_points
from cdm.data.priors2d import contour_map
from cdm.model.conditioning import mask_distance_transform
from cdm.render import _filter_and_crop, _footprint, _window_min

__all__ = ["kornia_ops", "kornia_project_points", "opencv_distance_transform"]


@torch.no_grad()
def opencv_distance_transform(mask: Tensor) -> Tensor:
    """OpenCV's precise L2 transform with :func:`mask_distance_transform`'s contract, as PC² computes it: the
    candidate, not adopted (its values for one mask changed between calls inside training; RESULTS.md)."""
    background = (mask[:, 0] <= 0.5).to(dtype=torch.uint8).numpy()
    s = background.shape[-1]
    dist = np.full(background.shape, math.sqrt(2.0) * s, dtype=np.float32)
    for image, out in zip(background, dist):
        if not image.all():
            out[...] = cv2.distanceTransform(image, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return torch.from_numpy(dist / s)[:, None].to(mask.dtype)


def kornia_project_points(points: Tensor, cameras: Cameras) -> Tensor:
    """``cdm.cameras.project_points`` through kornia: world → view by a 4×4 matrix (our row-vector ``R``
    transposed), then the pinhole ``K`` with the NDC focal and principal point; ``(B, N, 3)`` → NDC x, y and
    view depth. Equal for points in front of the camera (kornia does not clamp the depth of points behind)."""
    b = points.shape[0]
    world_to_view = torch.eye(4, dtype=points.dtype).repeat(b, 1, 1)
    world_to_view[:, :3, :3] = cameras.R.transpose(1, 2)
    world_to_view[:, :3, 3] = cameras.T
    view = transform_points(world_to_view, points)
    k = torch.eye(3, dtype=points.dtype).repeat(b, 1, 1)
    k[:, 0, 0] = k[:, 1, 1] = cameras.focal
    k[:, :2, 2] = cameras.principal
    return torch.cat([kcamera.project_points(view, k[:, None]), view[..., 2:]], dim=-1)


def _row(benchmark: str, case: str, a: Callable[[], Tensor], b: Callable[[], Tensor], repeats: int,
         difference: float, target: str) -> dict:
    timing = paired(a, b, repeats)
    return {"benchmark": benchmark, "case": f"{case}; max |a − b| {difference:.2g}", "without_s": timing.a_s,
            "with_s": timing.b_s, "ratio": timing.ratio, "target": target}


def _masks(size: int) -> Tensor:
    """``(8, 1, S, S)``: a centred box with a stray pixel, as silhouettes go; one image empty."""
    mask = torch.zeros(8, 1, size, size)
    mask[:, :, size // 4 : 3 * size // 4, size // 3 : 2 * size // 3] = 1.0
    mask[0, 0, 2, 2] = 1.0
    mask[1] = 0.0
    return mask


def _distance_rows(sizes: tuple[int, ...], repeats: int) -> list[dict]:
    rows = []
    for s in sizes:
        mask = _masks(s)
        ours = opencv_distance_transform(mask)
        diff = float((mask_distance_transform(mask) - ours).abs().max())
        rows.append(_row("mask distance transform: torch O(S³) vs OpenCV", f"B=8, {s}²",
                         lambda m=mask: mask_distance_transform(m), lambda m=mask: opencv_distance_transform(m),
                         repeats, diff, "<= 1 (OpenCV/torch)"))
        kdiff = float((kornia.contrib.distance_transform(mask[2:]) - ours[2:] * s).abs().max())  # in pixels
        rows.append(_row("mask distance transform: OpenCV vs kornia", f"B=8, {s}² (difference in pixels)",
                         lambda m=mask: opencv_distance_transform(m),
                         lambda m=mask: kornia.contrib.distance_transform(m),
                         max(3, repeats // 4), kdiff, "report (kornia/OpenCV)"))
    return rows


def _forward_backward(fn: Callable[[Tensor], Tensor], leaf: Tensor, upstream: Tensor) -> Callable[[], Tensor]:
    def run() -> Tensor:
        out = fn(leaf)
        out.backward(upstream)
        return out
    return run


def _projection_rows(cases: tuple[tuple[int, int], ...], repeats: int) -> list[dict]:
    rows = []
    for views, n in cases:
        one = torch.ones(views // 10)
        cams = orbit_cameras(20.0 * one, 30.0 * one, 3.0 * one, 10, focal=2.0).flatten()
        points = (torch.rand(views, n, 3, generator=torch.Generator().manual_seed(n)) - 0.5).requires_grad_()
        upstream = torch.randn(views, n, 3)
        with torch.no_grad():
            diff = float((project_points(points, cams) - kornia_project_points(points, cams)).abs().max())
        rows.append(_row("camera projection: ours vs kornia", f"{views} cameras × {n} points, fwd+bwd",
                         _forward_backward(lambda p, c=cams: project_points(p, c), points, upstream),
                         _forward_backward(lambda p, c=cams: kornia_project_points(p, c), points, upstream),
                         repeats, diff, "<= 1 to adopt (kornia/ours)"))
    return rows


def _filter_rows(cases: tuple[tuple[int, float, int, int], ...], repeats: int) -> list[dict]:
    """Cases ``(S, point size, M, C)``: planar renders have ``C = 1``, depth renders ``C = 2``; ``M = B·H``."""
    rows = []
    for s, point_size, m, c in cases:
        footprint = _footprint(point_size * s / 2.0)
        width = footprint.table.shape[0]
        canvas = torch.rand(m, c, s + width - 1, s + width - 1, generator=torch.Generator().manual_seed(s))
        canvas.requires_grad_()
        upstream = torch.randn(m, c, s, s)
        table = footprint.table.float()[None]

        def kornia_filter(x: Tensor, table: Tensor = table) -> Tensor:
            return kornia.filters.filter2d(x, table, border_type="constant", padding="valid")

        ours = _forward_backward(lambda x, f=footprint: _filter_and_crop(x, f), canvas, upstream)
        theirs = _forward_backward(kornia_filter, canvas, upstream)
        diff = float((ours() - theirs()).detach().abs().max())
        rows.append(_row("splat footprint filter: ours vs kornia filter2d",
                         f"{s}², point size {point_size} ({width}×{width} px), M={m}, C={c}, fwd+bwd",
                         ours, theirs, repeats, diff, "<= 1 to adopt (kornia/ours)"))
    return rows


def _window_min_rows(cases: tuple[tuple[int, int], ...], repeats: int) -> list[dict]:
    rows = []
    for s, half in cases:
        g = torch.Generator().manual_seed(s + half)
        zbuf = torch.rand(40, 1, s, s, generator=g) + 2.0
        zbuf[torch.rand(zbuf.shape, generator=g) < 0.7] = math.inf
        window = 2 * half + 1
        before = lambda z=zbuf, w=window: -F.max_pool2d(-z, w, stride=1, padding=w // 2)  # noqa: E731
        diff = float((before() - _window_min(zbuf, half)).nan_to_num(posinf=0.0).abs().max())
        rows.append(_row("front-layer window minimum: -max_pool2d(-z) vs kornia erosion",
                         f"M=40, {s}², {window}×{window} window", before,
                         lambda z=zbuf, h=half: _window_min(z, h), repeats, diff, "<= 1 (kornia/torch)"))
    return rows


def _contour_rows(sizes: tuple[int, ...], repeats: int) -> list[dict]:
    rows = []
    for s in sizes:
        images = torch.rand(8, 3, s, s, generator=torch.Generator().manual_seed(s))
        images = F.avg_pool2d(images, 5, stride=1, padding=2)  # some structure for the edges to follow
        ours = lambda x=images: torch.stack([contour_map(i) for i in x])  # noqa: E731
        theirs = lambda x=images: kornia.filters.canny(x, 100 / 255, 200 / 255)[1]  # noqa: E731
        differ = float((ours() != theirs()).float().mean())
        rows.append(_row("contour prior: OpenCV Canny vs kornia canny", f"B=8, {s}² (difference: share of pixels)",
                         ours, theirs, repeats, differ, "report (kornia/OpenCV; not the same detector)"))
    return rows


def kornia_ops(quick: bool, out_dir: str) -> list[dict]:
    """The rows of the module docstring; ``quick``: the smallest sizes, few repeats (a check that it runs)."""
    cv2.setNumThreads(1)
    r = 3 if quick else 21
    return [
        *_distance_rows((32,) if quick else (32, 64, 224), r),
        *_projection_rows(((40, 512),) if quick else ((40, 512), (80, 4096)), r),
        *_filter_rows(((64, 0.04, 40, 1),) if quick else (
            (64, 0.04, 40, 1), (64, 0.08, 40, 1), (64, 0.04, 80, 2), (224, 0.04, 40, 1), (224, 0.04, 80, 2),
            (224, 0.08, 80, 2)), r),
        *_window_min_rows(((64, 1),) if quick else ((64, 1), (64, 3), (224, 4), (224, 9)), r),
        *_contour_rows((64,) if quick else (64, 224), r),
    ]
