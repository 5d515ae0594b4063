"""The eight procedural shape categories: one small program each over the building blocks of
:mod:`cdm.data.procedural_parts`, whose sizes, proportions and optional parts are drawn from *continuous*
ranges, so no two objects are alike and nearest-image retrieval is a weak baseline (:mod:`cdm.evaluate`).
Objects are built Z-up in arbitrary units and turned to the world's +Y-up frame of :mod:`cdm.cameras`
(:func:`make_shape`); the data set that serves them is :mod:`cdm.data.procedural`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import trimesh

from cdm.data.procedural_parts import (
    Part,
    box,
    disc,
    lathe,
    rectangle_corners,
    rod,
    splayed_legs,
    tube,
    warped_box,
)
from cdm.data.views import Shape

__all__ = ["CATEGORIES", "GENERATOR_VERSION", "make_shape"]

# Z-up (how trimesh builds cylinders and lathes) → the world's Y-up: (x, y, z) ↦ (x, z, −y).
_Z_UP_TO_Y_UP = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def _u(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.uniform(low, high))


def _chair(rng: np.random.Generator) -> list[Part]:
    w = _u(rng, 0.8, 1.3)
    d = w * _u(rng, 0.8, 1.15)
    h = _u(rng, 0.7, 1.3)
    t = _u(rng, 0.05, 0.18)
    leg = _u(rng, 0.025, 0.08)
    square = rng.random() < 0.5
    inset = leg + _u(rng, 0.0, 0.12) * min(w, d)
    parts: list[Part] = [(box((w, d, t), (0, 0, h - t / 2)), 0)]
    parts += splayed_legs(rectangle_corners(w / 2 - inset, d / 2 - inset), h - t, _u(rng, 0.0, 0.12), leg, square)
    back_h = _u(rng, 0.5, 1.4)
    back_t = _u(rng, 0.04, 0.14)
    lean = math.tan(math.radians(_u(rng, 0.0, 22.0)))
    panel = _u(rng, 0.3, 1.0)  # fraction of the back filled by the panel; posts carry the rest
    back_w = (w - 4 * leg) * _u(rng, 0.8, 1.0)  # posts, when any, flank the panel
    y0 = -d / 2 + back_t / 2

    def back(v: np.ndarray) -> np.ndarray:
        z = h + (v[:, 2] + 0.5) * back_h * panel + back_h * (1 - panel)
        return np.stack([v[:, 0] * back_w, y0 + v[:, 1] * back_t - (z - h) * lean, z], axis=-1)

    parts.append((warped_box(back), 0))
    if panel < 0.95:
        for x in (-1, 1):
            post_x = x * (back_w / 2 + leg)
            parts.append((rod((post_x, y0, h), (post_x, y0 - back_h * lean, h + back_h), leg, square), 1))
    if rng.random() < 0.35:
        arm_h = h + _u(rng, 0.15, 0.35)
        arm_d = d * _u(rng, 0.5, 1.0)
        for x in (-1, 1):
            parts.append((box((2 * leg + 0.04, arm_d, 0.04), (x * w / 2, -d / 2 + arm_d / 2, arm_h)), 0))
            post = (x * w / 2, -d / 2 + arm_d - leg)
            parts.append((rod((*post, h), (*post, arm_h), leg, square), 1))
    return parts


def _table(rng: np.random.Generator) -> list[Part]:
    round_top = rng.random() < 0.35
    w = _u(rng, 1.0, 2.4)
    d = w if round_top else w * _u(rng, 0.45, 1.0)
    h = _u(rng, 0.6, 1.1)
    t = _u(rng, 0.03, 0.12)
    parts: list[Part] = [(disc(w / 2, t, h - t) if round_top else box((w, d, t), (0, 0, h - t / 2)), 0)]
    if rng.random() < (0.6 if round_top else 0.1):
        column = _u(rng, 0.04, 0.14)
        base_r = min(w, d) * _u(rng, 0.2, 0.45)
        base_t = _u(rng, 0.02, 0.08)
        parts.append((rod((0, 0, base_t), (0, 0, h - t), column, rng.random() < 0.3), 1))
        parts.append((disc(base_r, base_t, 0.0), 1))
        return parts
    leg = _u(rng, 0.025, 0.09)
    inset = leg + _u(rng, 0.0, 0.15) * min(w, d)
    reach = (w / 2 - inset) / (math.sqrt(2) if round_top else 1.0)
    half_y = reach if round_top else d / 2 - inset
    corners = rectangle_corners(reach, half_y)
    parts += splayed_legs(corners, h - t, _u(rng, 0.0, 0.06), leg, rng.random() < 0.6)
    if not round_top and rng.random() < 0.5:
        apron = _u(rng, 0.04, 0.15)
        z = h - t - apron / 2
        parts.append((box((2 * reach, 0.03, apron), (0, half_y, z)), 0))
        parts.append((box((2 * reach, 0.03, apron), (0, -half_y, z)), 0))
        parts.append((box((0.03, 2 * half_y, apron), (reach, 0, z)), 0))
        parts.append((box((0.03, 2 * half_y, apron), (-reach, 0, z)), 0))
    if rng.random() < 0.25:
        parts.append((box((2 * reach, 2 * half_y, 0.03), (0, 0, h * _u(rng, 0.12, 0.35))), 0))
    return parts


def _lamp(rng: np.random.Generator) -> list[Part]:
    base_r = _u(rng, 0.15, 0.35)
    base_t = _u(rng, 0.02, 0.08)
    if rng.random() < 0.7:
        base = disc(base_r, base_t, 0.0)
    else:
        base = box((2 * base_r, 2 * base_r, base_t), (0, 0, base_t / 2))
    pole_r = _u(rng, 0.012, 0.035)
    pole_h = _u(rng, 0.7, 1.8)
    parts: list[Part] = [(base, 0), (rod((0, 0, base_t), (0, 0, pole_h), pole_r, False), 0)]
    shade_bottom = _u(rng, 0.15, 0.4)
    shade_top = shade_bottom * _u(rng, 0.35, 0.95)
    shade_h = _u(rng, 0.15, 0.45)
    if rng.random() < 0.4:  # a desk lamp: an arm from the pole top, the shade hanging from its end
        angle = math.radians(_u(rng, -30.0, 50.0))
        arm = _u(rng, 0.3, 0.7)
        tip = (arm * math.cos(angle), 0.0, pole_h + arm * math.sin(angle))
        parts.append((rod((0, 0, pole_h), tip, pole_r, False), 0))
        shade_z, centre = tip[2] - shade_h, tip[:2]
    else:
        shade_z, centre = pole_h - shade_h * _u(rng, 0.3, 0.7), (0.0, 0.0)
    shade = lathe([[shade_bottom, 0.0], [shade_top, shade_h]], sections=32)
    parts.append((shade.apply_translation((centre[0], centre[1], shade_z)), 1))
    if rng.random() < 0.5:
        bulb = trimesh.creation.icosphere(subdivisions=1, radius=_u(rng, 0.04, 0.08))
        parts.append((bulb.apply_translation((centre[0], centre[1], shade_z + shade_h * 0.3)), 0))
    return parts


def _mug(rng: np.random.Generator) -> list[Part]:
    r0 = _u(rng, 0.3, 0.5)
    r1 = r0 * _u(rng, 0.85, 1.25)
    h = _u(rng, 0.6, 1.3)
    wall = _u(rng, 0.03, 0.08)
    body = lathe([[0, 0], [r0, 0], [r1, h], [r1 - wall, h], [r0 - wall, wall], [0, wall]], sections=32)
    major = h * _u(rng, 0.15, 0.32)
    minor = _u(rng, 0.025, 0.06)
    z = h * _u(rng, 0.4, 0.6)
    wall_r = r0 + (r1 - r0) * z / h - wall / 2
    reach = major * _u(rng, 0.8, 1.6)
    handle = tube((reach, major), (minor, minor * _u(rng, 0.6, 1.4)), (-math.pi / 2, math.pi / 2), 16, 10)
    handle.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0)))
    return [(body, 0), (handle.apply_translation((wall_r, 0, z)), 1 if rng.random() < 0.3 else 0)]


def _bottle(rng: np.random.Generator) -> list[Part]:
    rb = _u(rng, 0.22, 0.45)
    hb = _u(rng, 0.6, 1.5)
    hs = _u(rng, 0.1, 0.45)
    rn = rb * _u(rng, 0.2, 0.5)
    hn = _u(rng, 0.12, 0.5)
    waist = _u(rng, 0.8, 1.1)
    profile = [[0.0, 0.0], [rb * 0.92, 0.0], [rb, 0.04 * hb], [rb * waist, 0.5 * hb], [rb, hb]]
    for s in np.linspace(0.2, 1.0, 5):  # a cosine shoulder from body to neck
        profile.append([rn + (rb - rn) * 0.5 * (1 + math.cos(math.pi * s)), hb + hs * s])
    top = hb + hs + hn
    profile += [[rn, top - 0.02], [rn * 1.12, top - 0.01], [rn * 1.12, top], [0.0, top]]
    parts: list[Part] = [(lathe(profile, sections=28), 0)]
    if rng.random() < 0.5:
        cap_h = _u(rng, 0.05, 0.2)
        cap = trimesh.creation.cylinder(radius=rn * 1.18, height=cap_h, sections=24)
        parts.append((cap.apply_translation((0, 0, top + cap_h / 2 - 0.02)), 1))
    return parts


class _Wing(NamedTuple):
    """A tapered, swept slab from the root (y = 0) to the tip (|y| = span); angles in radians."""

    x0: float  # leading edge at the root
    z0: float
    span: float
    root: float  # chord at the root
    taper: float  # tip chord / root chord
    sweep: float
    dihedral: float
    thick: float


def _wing(spec: _Wing, side: int) -> trimesh.Trimesh:
    """One half of ``spec``; ``side`` = +1 or −1 picks the +Y or −Y half."""

    def warp(v: np.ndarray) -> np.ndarray:
        s = v[:, 1] + 0.5  # 0 at the root, 1 at the tip
        chord = spec.root * (1 - (1 - spec.taper) * s)
        x = spec.x0 + s * spec.span * math.tan(spec.sweep) + (v[:, 0] + 0.5) * chord
        z = spec.z0 + s * spec.span * math.tan(spec.dihedral) + v[:, 2] * spec.thick * (1 - 0.5 * s)
        return np.stack([x, side * s * spec.span, z], axis=-1)

    return warped_box(warp)


def _airplane(rng: np.random.Generator) -> list[Part]:
    length = _u(rng, 1.6, 2.6)
    radius = length * _u(rng, 0.035, 0.07)
    nose = length * _u(rng, 0.08, 0.2)
    tail = length * _u(rng, 0.2, 0.35)
    tail_r = radius * _u(rng, 0.15, 0.5)
    profile = [[0.0, 0.0]] + [[radius * math.sqrt(s), nose * s] for s in (0.1, 0.3, 0.6, 1.0)]
    profile += [[radius, length - tail], [tail_r, length], [0.0, length]]
    fuselage = lathe(profile, sections=20)
    fuselage.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0, 1, 0)))  # along +X

    main = _Wing(
        x0=length * _u(rng, 0.3, 0.5),
        z0=radius * _u(rng, -0.6, 0.5),
        span=length * _u(rng, 0.4, 0.7),
        root=length * _u(rng, 0.12, 0.25),
        taper=_u(rng, 0.3, 1.0),
        sweep=math.radians(_u(rng, 0.0, 40.0)),
        dihedral=math.radians(_u(rng, -3.0, 8.0)),
        thick=length * _u(rng, 0.01, 0.025),
    )
    tail_root = main.root * _u(rng, 0.4, 0.7)
    x_tail = length - tail_root * _u(rng, 1.0, 1.4)
    stabiliser = main._replace(
        x0=x_tail, z0=tail_r, span=main.span * _u(rng, 0.25, 0.45), root=tail_root, dihedral=0.0, thick=main.thick * 0.7
    )
    parts: list[Part] = [(fuselage, 0)]
    for side in (-1, 1):
        parts += [(_wing(main, side), 0), (_wing(stabiliser, side), 1)]
    fin_h = length * _u(rng, 0.1, 0.22)
    fin_sweep = math.tan(math.radians(_u(rng, 15.0, 50.0)))

    def fin(v: np.ndarray) -> np.ndarray:
        s = v[:, 2] + 0.5
        x = x_tail + s * fin_h * fin_sweep + (v[:, 0] + 0.5) * tail_root * (1 - 0.5 * s)
        return np.stack([x, v[:, 1] * stabiliser.thick, tail_r * 0.5 + s * fin_h], axis=-1)

    parts.append((warped_box(fin), 1))
    if rng.random() < 0.6:
        engine_r = radius * _u(rng, 0.35, 0.7)
        engine_l = main.root * _u(rng, 0.5, 0.9)
        for frac in (0.3, 0.6) if rng.random() < 0.3 else (_u(rng, 0.25, 0.45),):
            for side in (-1, 1):
                y = side * frac * main.span
                x = main.x0 + frac * main.span * math.tan(main.sweep) - engine_l * 0.3
                z = main.z0 + frac * main.span * math.tan(main.dihedral) - engine_r * 1.2
                parts.append((rod((x, y, z), (x + engine_l, y, z), engine_r, False), 1))
    return parts


def _sofa(rng: np.random.Generator) -> list[Part]:
    length = _u(rng, 1.3, 2.6)
    depth = _u(rng, 0.7, 1.05)
    seat = _u(rng, 0.3, 0.5)
    legs = _u(rng, 0.0, 0.12)
    cushion = _u(rng, 0.08, 0.18)
    back_t = _u(rng, 0.12, 0.3)
    back_h = _u(rng, 0.3, 0.65)
    lean = math.tan(math.radians(_u(rng, 0.0, 15.0)))
    arm_w = _u(rng, 0.08, 0.25) if rng.random() < 0.85 else 0.0
    arm_h = _u(rng, 0.05, 0.3)
    inner = length - 2 * arm_w
    base_top = seat - cushion
    # The base fits between the arms so no surface hides inside another part (it would be in the GT).
    parts: list[Part] = [(box((inner, depth, base_top - legs), (0, 0, (legs + base_top) / 2)), 0)]
    seats = int(np.clip(round(inner / _u(rng, 0.6, 0.9)), 1, 3))
    gap = 0.015
    width = (inner - gap * (seats + 1)) / seats
    seat_d = depth - back_t
    for k in range(seats):
        x = -inner / 2 + gap + width / 2 + k * (width + gap)
        parts.append((box((width, seat_d - gap, cushion), (x, back_t / 2, base_top + cushion / 2)), 0))

    def back(v: np.ndarray) -> np.ndarray:
        z = base_top + (v[:, 2] + 0.5) * (cushion + back_h)
        y = -depth / 2 + back_t / 2 + v[:, 1] * back_t - (z - base_top) * lean
        return np.stack([v[:, 0] * inner, y, z], axis=-1)

    parts.append((warped_box(back), 0))
    if arm_w > 0:
        for side in (-1, 1):
            centre = (side * (length - arm_w) / 2, 0, (legs + seat + arm_h) / 2)
            parts.append((box((arm_w, depth, seat + arm_h - legs), centre), 0))
    if legs > 0.02:
        corners = rectangle_corners(length / 2 - 0.05, depth / 2 - 0.05)
        parts += splayed_legs(corners, legs, 0.0, _u(rng, 0.015, 0.04), rng.random() < 0.5)
    return parts


def _ring(rng: np.random.Generator) -> list[Part]:
    minor = _u(rng, 0.06, 0.35)
    squash = _u(rng, 0.75, 1.0)
    band = tube((1.0, squash), (minor, minor * _u(rng, 0.5, 1.6)), (0.0, 2 * math.pi), 40, 14)
    parts: list[Part] = [(band, 0)]
    if rng.random() < 0.4:
        gem_r = _u(rng, 0.1, 0.25)
        gem = trimesh.creation.icosphere(subdivisions=1, radius=gem_r)
        parts.append((gem.apply_translation((0, squash + minor + gem_r * 0.6, 0)), 1))
    tilt = trimesh.transformations.rotation_matrix(math.radians(_u(rng, 0.0, 90.0)), (1, 0, 0))
    return [(mesh.apply_transform(tilt), material) for mesh, material in parts]


_BUILDERS: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "airplane": _airplane,
    "bottle": _bottle,
    "chair": _chair,
    "lamp": _lamp,
    "mug": _mug,
    "ring": _ring,
    "sofa": _sofa,
    "table": _table,
}

CATEGORIES: tuple[str, ...] = tuple(_BUILDERS)
"""The procedural categories, sorted."""


def make_shape(category: str, rng: np.random.Generator) -> Shape:
    """Build one random object of ``category`` (a name in :data:`CATEGORIES`).

    Returns:
        the mesh in the world frame (+Y up, un-normalised units) and its ``(F,)`` per-face material
        index (0 main, 1 accent). The same ``rng`` state gives the same object.
    """
    if category not in _BUILDERS:
        raise ValueError(f"unknown procedural category {category!r}; allowed: {', '.join(CATEGORIES)}")
    parts = _BUILDERS[category](rng)
    mesh = trimesh.util.concatenate([mesh for mesh, _ in parts])
    mesh.apply_transform(_Z_UP_TO_Y_UP)
    material = np.concatenate([np.full(len(m.faces), k, dtype=np.int64) for m, k in parts])
    return Shape(mesh, material)


GENERATOR_VERSION = 3
"""Raised whenever a change to this module or :mod:`cdm.data.procedural_parts` changes the objects a seed produces
(recorded with each run)."""
