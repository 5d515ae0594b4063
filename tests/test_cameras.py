"""Tests for cdm.cameras: PyTorch3D conventions by hand-computed projections, view selection."""

import math

import pytest
import torch

from cdm.cameras import (
    Cameras,
    look_at_cameras,
    ndc_to_pixel,
    orbit_cameras,
    pixel_centers_ndc,
    project_points,
    select_sequence_views,
    world_to_view,
)


def _front_camera(dist: float = 3.0) -> Cameras:
    """Camera on world +Z at ``dist``, looking at the origin, focal 2 (batch (1,))."""
    return look_at_cameras(torch.tensor([0.0]), torch.tensor([0.0]), torch.tensor([dist]))


def test_look_at_front_camera_axes_match_pytorch3d():
    cam = _front_camera(3.0)
    # View +X = world −X (image left), +Y = world +Y, +Z = world −Z (towards the origin).
    expected_R = torch.tensor([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    torch.testing.assert_close(cam.R[0], expected_R)
    torch.testing.assert_close(cam.T[0], torch.tensor([0.0, 0.0, 3.0]))


def test_world_plus_x_lands_on_the_image_right_half():
    cam = _front_camera(3.0)
    proj = project_points(torch.tensor([[[0.45, 0.75, 0.0], [-0.45, -0.75, 0.0]]]), cam)
    # x_ndc = f·X/Z = 2·(−0.45)/3 = −0.3 (right half), y_ndc = 2·0.75/3 = 0.5 (top half), z = 3.
    torch.testing.assert_close(proj[0], torch.tensor([[-0.3, 0.5, 3.0], [0.3, -0.5, 3.0]]))
    pix = ndc_to_pixel(proj[..., :2], 10)
    # col = (1 − x)·S/2 − 0.5, row = (1 − y)·S/2 − 0.5 at S = 10.
    torch.testing.assert_close(pix[0], torch.tensor([[6.0, 2.0], [3.0, 7.0]]))


def test_camera_centre_and_origin_projection_for_any_pose():
    elev = torch.tensor([10.0, -35.0, 60.0])
    azim = torch.tensor([0.0, 90.0, 222.0])
    dist = torch.tensor([2.0, 2.5, 4.0])
    cams = look_at_cameras(elev, azim, dist)
    e, a = torch.deg2rad(elev), torch.deg2rad(azim)
    centre = torch.stack([dist * e.cos() * a.sin(), dist * e.sin(), dist * e.cos() * a.cos()], dim=-1)
    # Camera centre C satisfies C·R + T = 0; R is a rotation.
    torch.testing.assert_close(world_to_view(centre[:, None], cams)[:, 0], torch.zeros(3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(cams.R @ cams.R.transpose(1, 2), torch.eye(3).expand(3, 3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(torch.linalg.det(cams.R), torch.ones(3))
    origin = project_points(torch.zeros(3, 1, 3), cams)[:, 0]
    torch.testing.assert_close(origin, torch.stack([torch.zeros(3), torch.zeros(3), dist], dim=-1), atol=1e-5, rtol=0)
    # World +Y stays up in the image (NDC y > 0) for cameras that are not overhead.
    up = project_points(torch.tensor([0.0, 0.3, 0.0]).expand(3, 1, 3), cams)[:, 0]
    assert (up[:, 1] > 0).all()


def test_pixel_centres_map_to_integer_pixels():
    centres = pixel_centers_ndc(7)
    pix = ndc_to_pixel(centres, 7)
    rows, cols = torch.meshgrid(torch.arange(7.0), torch.arange(7.0), indexing="ij")
    torch.testing.assert_close(pix, torch.stack([cols, rows], dim=-1), atol=1e-5, rtol=0)
    assert centres[0, 0, 0] > 0 and centres[0, 0, 1] > 0  # pixel [0, 0] is at NDC +X (left), +Y (top)


def test_orbit_view_zero_is_the_input_camera_and_views_are_evenly_spaced():
    elev, azim, dist = torch.tensor([20.0, -5.0]), torch.tensor([30.0, 300.0]), torch.tensor([2.5, 3.0])
    num_views = 5
    views = orbit_cameras(elev, azim, dist, num_views)
    assert views.batch_shape == (2, num_views)
    single = look_at_cameras(elev, azim, dist)
    torch.testing.assert_close(views.R[:, 0], single.R)
    torch.testing.assert_close(views.T[:, 0], single.T)
    torch.testing.assert_close(views.focal[:, 0], single.focal)
    # Camera centres C = −T·Rᵀ: same elevation and distance, azimuth steps of 360/H degrees.
    centres = -(views.T[..., None, :] @ views.R.transpose(-1, -2))[..., 0, :]
    torch.testing.assert_close(centres.norm(dim=-1), dist[:, None].expand(2, num_views))
    azimuths = torch.rad2deg(torch.atan2(centres[..., 0], centres[..., 2]))
    steps = torch.remainder(azimuths.diff(dim=1), 360.0)
    torch.testing.assert_close(steps, torch.full((2, num_views - 1), 360.0 / num_views), atol=1e-3, rtol=0)
    flat = views.flatten()
    assert flat.batch_shape == (2 * num_views,)
    torch.testing.assert_close(flat.R[num_views + 1], views.R[1, 1])


def test_select_sequence_views_even_spacing_with_wraparound():
    assert select_sequence_views(100, 7, 4) == [7, 32, 57, 82]
    assert select_sequence_views(10, 8, 4) == [8, 0, 3, 5]  # steps of 2.5 floored, wrapping at 10
    views = select_sequence_views(37, 30, 10)
    assert views[0] == 30 and len(set(views)) == 10
    gaps = [(b - a) % 37 for a, b in zip(views, views[1:] + views[:1])]
    assert set(gaps) <= {math.floor(37 / 10), math.ceil(37 / 10)}
    with pytest.raises(ValueError, match="num_views"):
        select_sequence_views(10, 0, 0)


def test_cameras_indexing_and_repeat_interleave():
    cams = look_at_cameras(torch.tensor([0.0, 10.0]), torch.tensor([0.0, 45.0]), torch.tensor([2.0, 3.0]))
    rep = cams.repeat_interleave(3)
    assert len(rep) == 6
    torch.testing.assert_close(rep.T[3:], cams.T[1:].expand(3, 3))
    torch.testing.assert_close(cams[1].T, cams.T[1])
