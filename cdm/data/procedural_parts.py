"""The building blocks of the procedural shapes (:mod:`cdm.data.procedural_shapes`): boxes, warped boxes,
bars, lathes, discs, tubes and splayed legs, each a trimesh mesh built Z-up in the shapes' arbitrary units."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import trimesh
from trimesh.geometry import align_vectors

Part = tuple[trimesh.Trimesh, int]
"""A mesh and its material index (0 = the object's main colour, 1 = its accent colour)."""


def box(extents, center) -> trimesh.Trimesh:
    """An axis-aligned box of ``extents`` (x, y, z) centred on ``center``."""
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def warped_box(warp: Callable[[np.ndarray], np.ndarray]) -> trimesh.Trimesh:
    """A hexahedron: the unit box's corners, (8, 3) in {−½, ½}³, moved by ``warp`` (tapers, sweeps, tilts)."""
    unit = trimesh.creation.box()
    return trimesh.Trimesh(warp(np.asarray(unit.vertices)), unit.faces, process=False)


def rod(p0, p1, radius: float, square: bool) -> trimesh.Trimesh:
    """A round or square bar of half-width ``radius`` from ``p0`` to ``p1``."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    if not square:
        return trimesh.creation.cylinder(radius=radius, segment=np.stack([p0, p1]), sections=12)
    axis = p1 - p0
    bar = trimesh.creation.box(extents=(2 * radius, 2 * radius, float(np.linalg.norm(axis))))
    transform = align_vectors([0.0, 0.0, 1.0], axis)
    transform[:3, 3] = (p0 + p1) / 2
    return bar.apply_transform(transform)


def lathe(profile, sections: int = 24) -> trimesh.Trimesh:
    """Surface of revolution about +Z of a ``(K, 2)`` (radius, z) profile; closed where it meets the axis."""
    return trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)


def disc(radius: float, height: float, bottom: float) -> trimesh.Trimesh:
    """A flat cylinder about +Z standing on ``z = bottom``."""
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=32)
    return mesh.apply_translation((0.0, 0.0, bottom + height / 2))


def tube(
    radii: tuple[float, float], section: tuple[float, float], arc: tuple[float, float], n_u: int = 32, n_v: int = 12
) -> trimesh.Trimesh:
    """A torus (or an arc of one) in the XY plane about the origin.

    ``radii`` are the centre line's semi-axes along X and Y, ``section`` the tube's radius in the
    plane and along Z, ``arc`` the range of the centre-line angle (radians); a full turn closes it.
    """
    closed = arc[1] - arc[0] >= 2 * math.pi - 1e-9
    u = np.linspace(arc[0], arc[1], n_u + (0 if closed else 1), endpoint=not closed)
    v = np.linspace(0.0, 2 * math.pi, n_v, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    radial = np.stack([np.cos(uu), np.sin(uu), np.zeros_like(uu)], axis=-1)
    centre = np.stack([radii[0] * np.cos(uu), radii[1] * np.sin(uu), np.zeros_like(uu)], axis=-1)
    verts = centre + section[0] * np.cos(vv)[..., None] * radial
    verts[..., 2] += section[1] * np.sin(vv)
    rows = len(u) if closed else len(u) - 1
    i, j = np.meshgrid(np.arange(rows), np.arange(n_v), indexing="ij")
    a = i * n_v + j
    b = ((i + 1) % len(u)) * n_v + j
    c = ((i + 1) % len(u)) * n_v + (j + 1) % n_v
    d = i * n_v + (j + 1) % n_v
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(verts.reshape(-1, 3), faces, process=False)


def splayed_legs(corners: np.ndarray, top: float, splay: float, radius: float, square: bool) -> list[Part]:
    """Four legs from ``(4, 2)`` xy ``corners`` at height ``top`` to the floor, splayed outwards."""
    parts = []
    for x, y in corners:
        foot = (x + np.sign(x) * splay, y + np.sign(y) * splay, 0.0)
        parts.append((rod((x, y, top), foot, radius, square), 1))
    return parts


def rectangle_corners(half_x: float, half_y: float) -> np.ndarray:
    """The ``(4, 2)`` xy corners ``(±half_x, ±half_y)`` of a rectangle about the origin."""
    return np.array([[half_x, half_y], [-half_x, half_y], [half_x, -half_y], [-half_x, -half_y]])
