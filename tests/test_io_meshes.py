"""cdm/io/meshes.py: meshes and point clouds parsed from bytes read within a cap, each refusal one line."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from cdm.io.meshes import read_mesh, read_vertices


def test_a_mesh_and_a_cloud_read_as_trimesh_reads_them(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.export(tmp_path / "box.obj")
    mesh = read_mesh(tmp_path / "box.obj", "data.root")
    assert len(mesh.faces) == 12 and mesh.area == pytest.approx(22.0)
    points = np.arange(48, dtype=np.float64).reshape(16, 3)
    trimesh.PointCloud(points).export(tmp_path / "cloud.ply")
    assert np.allclose(read_vertices(tmp_path / "cloud.ply", "data.root"), points)


def test_garbage_a_cloud_as_a_mesh_and_a_fifo_are_one_line_each(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(ValueError, match="^data.root: cannot read mesh .*bad.ply"):
        read_mesh(tmp_path / "bad.ply", "data.root")
    trimesh.PointCloud(np.zeros((16, 3))).export(tmp_path / "cloud.ply")
    with pytest.raises(ValueError, match="cloud.ply holds no triangles"):
        read_mesh(tmp_path / "cloud.ply", "data.root")
    os.mkfifo(tmp_path / "fifo.obj")  # no writer: trimesh's own open would wait forever
    with pytest.raises(ValueError, match="is a FIFO; expected a regular file"):
        read_mesh(tmp_path / "fifo.obj", "data.root")
