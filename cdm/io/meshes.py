"""Meshes and point clouds a user or a data set wrote (OBJ, PLY, OFF, STL, GLB), parsed by trimesh from bytes
read within a cap.

trimesh opens a path it is given without asking what it is (a FIFO blocks it, ``/dev/zero`` reads forever)
and its parsers index, unpack and decode blindly. So the file is read here first, as a regular file of at
most :data:`MAX_MESH_BYTES` (:func:`cdm.io.files.read_bounded`), and trimesh parses the bytes; whatever its
parsers raise on a malformed file becomes one ``ValueError`` naming the file.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import trimesh

from cdm.io.arrays import MAX_ARRAY_BYTES
from cdm.io.files import read_bounded

__all__ = ["MAX_MESH_BYTES", "read_mesh", "read_vertices"]

MAX_MESH_BYTES = MAX_ARRAY_BYTES
"""Most bytes of a mesh or point-cloud file read (as of one array: 512 MiB)."""

_PARSE_ERRORS = (ValueError, IndexError, KeyError, TypeError, EOFError, OSError, MemoryError, struct.error)
"""What trimesh's loaders raise on malformed files."""


def _parse(path: Path, label: str, what: str, **kwargs) -> object:
    data = read_bounded(path, label, MAX_MESH_BYTES)
    try:
        return trimesh.load(io.BytesIO(data), file_type=path.suffix.lower().lstrip("."), **kwargs)
    except _PARSE_ERRORS as exc:
        raise ValueError(f"{label}: cannot read {what} {path}: {type(exc).__name__}: {exc}") from None


def read_mesh(path: Path, label: str) -> trimesh.Trimesh:
    """The mesh file ``path`` as one triangle mesh (a scene's meshes concatenated, transforms applied);
    ValueError starting with ``label`` when it cannot be parsed or holds no triangles with area."""
    mesh = _parse(path, label, "mesh", force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{label}: {path} holds no triangles (empty, corrupt or a point cloud); remove or fix it")
    if not (np.all(np.isfinite(mesh.vertices)) and mesh.area > 0):
        raise ValueError(f"{label}: {path} has non-finite vertices or zero surface area; remove or fix it")
    return mesh


def read_vertices(path: Path, label: str) -> np.ndarray:
    """The ``(N, 3)`` float64 vertices of the point-cloud (or mesh) file ``path``, ``(0, 3)`` when it holds
    none; ValueError starting with ``label`` when it cannot be parsed."""
    loaded = _parse(path, label, "point cloud")
    return np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
