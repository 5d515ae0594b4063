"""Small ShapeNet-R2N2 and Co3D v2 trees in their exact published layouts, for tests and benchmarks.

Every image is rendered from the object's dense cloud with the *data set's own* camera model, written
out independently of :mod:`cdm.cameras`: R2N2's cameras as PyTorch3D's R2N2 reader computes them from
the metadata (in the ShapeNet v1 frame R2N2 rendered, with the PC15k cloud stored in PointFlow's v2
frame, as published) and Co3D's PyTorch3D NDC formulas on non-square images. A loader that converts
either camera or frame wrongly projects the ground truth off the mask.

Objects are an asymmetric "L" of two boxes, so a mirrored or rotated camera does not go unnoticed.
"""

from __future__ import annotations

import gzip
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh

SHAPENET_SYNSETS = {"chair": "03001627", "airplane": "02691156"}


def l_shape(rng: np.random.Generator, count: int, extent: float = 0.9) -> np.ndarray:
    """``(count, 3)`` surface samples of an L of two boxes, random proportions, centred, longest side ``extent``."""
    a = trimesh.creation.box(extents=[0.9, rng.uniform(0.15, 0.3), rng.uniform(0.3, 0.6)])
    b = trimesh.creation.box(extents=[rng.uniform(0.15, 0.3), rng.uniform(0.5, 0.8), rng.uniform(0.3, 0.6)])
    b.apply_translation([0.45 - b.extents[0] / 2, b.extents[1] / 2, 0.0])
    mesh = trimesh.util.concatenate([a, b])
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    lo, hi = points.min(0), points.max(0)
    return (points - (lo + hi) / 2) * (extent / (hi - lo).max())


def splat(u: np.ndarray, v: np.ndarray, z: np.ndarray, colour: np.ndarray, height: int, width: int, radius: float):
    """Rasterise points at pixel coords (u right, v down; pixel (i, j) spans [j, j+1) × [i, i+1)) as
    discs; returns ``(rgb (H, W, 3) uint8, covered (H, W) bool, depth (H, W) float, 0 where empty)``."""
    rgb = np.zeros((height, width, 3), np.uint8)
    depth = np.full((height, width), np.inf)
    order = np.argsort(-z)  # far to near: nearer points overwrite
    u, v, z, colour = u[order], v[order], z[order], colour[order]
    reach = math.ceil(radius)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            col, row = np.floor(u + dx).astype(int), np.floor(v + dy).astype(int)
            near = (col + 0.5 - u) ** 2 + (row + 0.5 - v) ** 2 <= radius**2
            ok = near & (col >= 0) & (col < width) & (row >= 0) & (row < height)
            rgb[row[ok], col[ok]] = colour[ok]
            np.minimum.at(depth, (row[ok], col[ok]), z[ok])
    covered = np.isfinite(depth)
    return rgb, covered, np.where(covered, depth, 0.0)


def _colours(points: np.ndarray) -> np.ndarray:
    return (np.clip(0.5 + points / (2 * np.abs(points).max()), 0, 1) * 200 + 30).astype(np.uint8)


# --- ShapeNet: R2N2 renderings + PointFlow PC15k -----------------------------------------------------


def r2n2_pixels(points: np.ndarray, azimuth: float, elevation: float, distance: float, size: int = 137):
    """Project ShapeNet **v1** points with the camera PyTorch3D's R2N2 reader builds from a metadata line
    (``compute_extrinsic_matrix``, then ``_compute_camera_calibration`` and ``K`` with focal 2.1875, as in
    ``pytorch3d/datasets/r2n2``), written with 4×4 matrices as there; ``(u, v, depth)`` in pixels."""
    a, e = -math.radians(azimuth), -math.radians(elevation)
    sa, ca, se, ce = math.sin(a), math.cos(a), math.sin(e), math.cos(e)
    world_to_obj = np.array([[ca * ce, sa * ce, -se], [-sa, ca, 0.0], [ca * se, sa * se, ce]])
    obj_to_cam = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    rt = np.eye(4)
    rt[:3, :3] = obj_to_cam @ world_to_obj
    rt[:3, 3] = -(obj_to_cam @ np.array([distance, 0.0, 0.0]))
    blender_obj_import = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])  # Y up → Z up
    rt = (rt @ blender_obj_import).T @ np.diag([-1.0, 1.0, -1.0, 1.0])  # ShapeNet → PyTorch3D world
    view = points @ rt[:3, :3] + rt[3, :3]
    x, y = 2.1875 * view[:, 0] / view[:, 2], 2.1875 * view[:, 1] / view[:, 2]
    return size / 2 * (1 - x), size / 2 * (1 - y), view[:, 2]  # NDC +X left, +Y up → pixels


def v1_to_v2(points: np.ndarray) -> np.ndarray:
    """ShapeNet v1 → v2 model frame: the inverse of BDM's ``transform_v2_to_v1`` (``(x, y, z)_v1 = (−z, y, −x)_v2``)."""
    return np.stack([-points[:, 2], points[:, 1], -points[:, 0]], axis=1)


@dataclass
class ShapeNetTree:
    root: Path
    splits: dict[str, dict[str, list[str]]] = field(default_factory=dict)
    """category → published split → model ids with renderings."""
    unrendered: list[str] = field(default_factory=list)
    bdm_split: dict[str, dict[str, list[str]]] = field(default_factory=dict)
    """R2N2 split (train/test) → category → model ids, as written to BDM's ``pc_dict_v2.json`` (if asked)."""
    offset: np.ndarray = field(default_factory=lambda: np.array([0.03, -0.05, 0.02]))


def make_shapenet(root: Path, per_split: dict[str, int] | None = None, seed: int = 0, views: int = 24,
                  bdm_split: bool = False, synsets: dict[str, str] | None = None) -> ShapeNetTree:
    """``root/ShapeNetRendering`` and ``root/ShapeNetCore.v2.PC15k`` for chair and airplane.

    Each category gets ``per_split`` models per PC15k split (default train 3, val 1, test 1), plus one
    train model without renderings (PC15k has models R2N2 never rendered). Each object lives in the v1
    frame shifted by ``offset`` (as if not centred); renderings are made there, as R2N2 rendered v1
    meshes, and the PC15k cloud is written in the v2 frame, as PointFlow sampled v2 meshes.
    ``bdm_split`` also writes BDM's ``pc_dict_v2.json``: R2N2's test split = PC15k's test models plus the
    first train model, its train split = the other rendered models (each mapped to its PC15k folder).
    ``synsets`` (name → synset id) replaces chair and airplane, e.g. with all 13 R2N2 classes.
    """
    synsets = synsets or SHAPENET_SYNSETS
    per_split = per_split or {"train": 3, "val": 1, "test": 1}
    rng = np.random.default_rng(seed)
    tree = ShapeNetTree(root)
    for name, synset in synsets.items():
        tree.splits[name] = {}
        for split, count in per_split.items():
            models = [f"{name[:2]}{split}{k:03d}{rng.integers(1 << 30):08x}" for k in range(count)]
            tree.splits[name][split] = models
            for model in models + ([f"{name[:2]}norender"] if split == "train" else []):
                dense = l_shape(rng, 15000, extent=0.7)  # R2N2 frames keep the whole object in view
                rot = trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * math.pi), [0, 1, 0])[:3, :3]
                dense = dense @ rot.T
                cloud_dir = root / "ShapeNetCore.v2.PC15k" / synset / split
                cloud_dir.mkdir(parents=True, exist_ok=True)
                np.save(cloud_dir / f"{model}.npy", v1_to_v2(dense + tree.offset).astype(np.float32))
                if "norender" in model:
                    tree.unrendered.append(model)
                    continue
                _render_r2n2(root / "ShapeNetRendering" / synset / model / "rendering", dense + tree.offset, rng, views)
    if bdm_split:
        table: dict[str, dict[str, dict[str, str]]] = {"train": {}, "test": {}}
        for name, synset in synsets.items():
            moved = tree.splits[name]["train"][0]
            for folder, models in tree.splits[name].items():
                for model in models:
                    r2n2 = "test" if folder == "test" or model == moved else "train"
                    table[r2n2].setdefault(synset, {})[model] = folder
                    tree.bdm_split.setdefault(r2n2, {}).setdefault(name, []).append(model)
        (root / "pc_dict_v2.json").write_text(json.dumps(table, indent=1))
    return tree


def _render_r2n2(folder: Path, dense: np.ndarray, rng: np.random.Generator, views: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    lines, names = [], []
    colour = _colours(dense)
    for k in range(views):
        az, el, ratio = rng.uniform(0, 360), rng.uniform(25, 30), rng.uniform(0.8, 0.95)
        u, v, z = r2n2_pixels(dense, az, el, ratio * 1.75)
        rgb, covered, _ = splat(u, v, z, colour, 137, 137, radius=1.0)
        bgra = np.concatenate([rgb[..., ::-1], (covered * 255).astype(np.uint8)[..., None]], axis=2)
        bgra[~covered] = 0
        cv2.imwrite(str(folder / f"{k:02d}.png"), bgra)
        lines.append(f"{az:.6f} {el:.6f} 0 {ratio:.6f} 25")
        names.append(f"{k:02d}.png")
    (folder / "rendering_metadata.txt").write_text("\n".join(lines) + "\n")
    (folder / "renderings.txt").write_text("\n".join(names) + "\n")


# --- Co3D v2 ----------------------------------------------------------------------------------------


def co3d_pixels(points: np.ndarray, R: np.ndarray, T: np.ndarray, focal, principal, height: int, width: int):
    """PyTorch3D camera with ``ndc_isotropic`` intrinsics → ``(u, v, view depth)`` in pixels."""
    view = points @ R + T
    x = focal[0] * view[:, 0] / view[:, 2] + principal[0]
    y = focal[1] * view[:, 1] / view[:, 2] + principal[1]
    half = min(height, width) / 2.0
    return width / 2.0 - x * half, height / 2.0 - y * half, view[:, 2]


def write_ply(path: Path, points: np.ndarray, colours: np.ndarray) -> None:
    """Binary little-endian PLY with float xyz and uchar rgb, as Co3D publishes its point clouds."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    record = np.zeros(len(points), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    record["xyz"], record["rgb"] = points, colours
    path.write_bytes(header.encode() + record.tobytes())


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> tuple[np.ndarray, np.ndarray]:
    """PyTorch3D world→view ``(R, T)``: columns of R are the view axes (+X left, +Y up, +Z forward)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z], axis=1)
    return R, -eye @ R


@dataclass
class Co3DTree:
    root: Path
    sequences: dict[str, dict[str, list[str]]] = field(default_factory=dict)
    """category → set-list split → sequence names (with point clouds)."""
    no_cloud: dict[str, str] = field(default_factory=dict)
    scale_adjustment: float = 0.8


CO3D_SPLITS = {"train": 2, "val": 1, "test": 1}


def make_co3d(root: Path, categories=("teddybear", "hydrant"), frames: int = 6, seed: int = 0,
              upscale: int = 1, splits: dict[str, int] | None = None,
              sequence_names: dict[str, list[str]] | None = None) -> Co3DTree:
    """``root/<category>/...`` with ``splits`` sequences per set-list split (default train 2, val 1, test 1)
    plus a train sequence without a point cloud. ``sequence_names`` (split → names) renames the first sequences
    with clouds of a split in every category (e.g. to names on PC²'s lists). Images are 96×72 or
    64×88 (× ``upscale``) JPEGs; the world frame is the L shape scaled ×2.5, rotated and shifted; fx ≠ fy and an
    off-centre principal point exercise the crop camera."""
    rng = np.random.default_rng(seed)
    tree = Co3DTree(root)
    for category in categories:
        folder = root / category
        frame_entries, seq_entries, set_lists = [], [], {"train": [], "val": [], "test": []}
        tree.sequences[category] = {}
        for split, count in (splits or CO3D_SPLITS).items():
            names = [
                f"{rng.integers(100, 999)}_{rng.integers(10000, 99999)}_{k}" for k in range(count + (split == "train"))
            ]
            given = (sequence_names or {}).get(split, [])
            names[: len(given)] = given
            tree.sequences[category][split] = names[:count]
            for index, seq in enumerate(names):
                has_cloud = index < count
                if not has_cloud:
                    tree.no_cloud[category] = seq
                size = (72, 96) if index % 2 == 0 else (88, 64)
                entries = _co3d_sequence(
                    folder, category, seq, rng, frames, size, upscale, tree.scale_adjustment, has_cloud
                )
                frame_entries += entries
                set_lists[split] += [[seq, e["frame_number"], e["image"]["path"]] for e in entries]
                cloud = (
                    {"path": f"{category}/{seq}/pointcloud.ply", "quality_score": 1.0, "n_points": 6010}
                    if has_cloud
                    else None
                )
                seq_entries.append(
                    {
                        "sequence_name": seq,
                        "category": category,
                        "video": {"path": f"{category}/{seq}/video.mp4", "length": frames},
                        "point_cloud": cloud,
                        "viewpoint_quality_score": 1.0,
                    }
                )
        (folder / "frame_annotations.jgz").write_bytes(gzip.compress(json.dumps(frame_entries).encode()))
        (folder / "sequence_annotations.jgz").write_bytes(gzip.compress(json.dumps(seq_entries).encode()))
        (folder / "set_lists").mkdir()
        (folder / "set_lists" / "set_lists_fewview_dev.json").write_text(json.dumps(set_lists))
    return tree


def _co3d_sequence(folder: Path, category: str, seq: str, rng: np.random.Generator, frames: int, size: tuple[int, int],
                   upscale: int, scale_adjustment: float, has_cloud: bool) -> list[dict]:
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    centre = rng.uniform(-3, 3, 3)
    world = l_shape(rng, 6000) * 2.5 @ rot.T + centre
    colour = _colours(world - centre)
    seq_dir = folder / seq
    for sub in ("images", "masks", "depths", "depth_masks"):
        (seq_dir / sub).mkdir(parents=True, exist_ok=True)
    if has_cloud:
        outliers = centre + rng.normal(0, 40, (10, 3))  # Co3D clouds carry a few stray points
        write_ply(
            seq_dir / "pointcloud.ply",
            np.concatenate([world, outliers]),
            np.concatenate([colour, np.zeros((10, 3), np.uint8)]),
        )
    h, w = size
    focal = [2.2, 2.2 * 1.04]
    principal = [0.04, -0.03]
    start = rng.uniform(0, 2 * math.pi)
    entries = []
    for k in range(frames):
        angle = start + 2 * math.pi * k / frames
        eye = centre + rng.uniform(5.5, 6.5) * np.array([math.cos(angle), rng.uniform(0.2, 0.5), math.sin(angle)])
        R, T = _look_at(eye, centre + rng.normal(0, 0.1, 3), rng.uniform(-0.2, 0.2))
        u, v, z = co3d_pixels(world, R, T, focal, principal, h, w)
        rgb, covered, depth = splat(u, v, z, colour, h, w, radius=1.2)
        background = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        image = np.where(covered[..., None], rgb, background)
        mask = (covered * 255).astype(np.uint8)
        stored = (depth / scale_adjustment).astype(np.float16).view(np.uint16)
        if upscale > 1:
            big = (w * upscale, h * upscale)
            image, mask = (
                cv2.resize(image, big, interpolation=cv2.INTER_LINEAR),
                cv2.resize(mask, big, interpolation=cv2.INTER_NEAREST),
            )
            stored = cv2.resize(stored, big, interpolation=cv2.INTER_NEAREST)
        number = k + 1
        name = f"frame{number:06d}"
        rel = f"{category}/{seq}"
        cv2.imwrite(str(seq_dir / "images" / f"{name}.jpg"), image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        cv2.imwrite(str(seq_dir / "masks" / f"{name}.png"), mask)
        cv2.imwrite(str(seq_dir / "depths" / f"{name}.jpg.geometric.png"), stored)
        cv2.imwrite(str(seq_dir / "depth_masks" / f"{name}.png"), mask)
        entries.append({
            "sequence_name": seq, "frame_number": number, "frame_timestamp": k / 30.0,
            "image": {"path": f"{rel}/images/{name}.jpg", "size": [h * upscale, w * upscale]},
            "depth": {"path": f"{rel}/depths/{name}.jpg.geometric.png", "scale_adjustment": scale_adjustment,
                      "mask_path": f"{rel}/depth_masks/{name}.png"},
            "mask": {"path": f"{rel}/masks/{name}.png", "mass": float(covered.sum())},
            "viewpoint": {"R": R.tolist(), "T": T.tolist(), "focal_length": focal, "principal_point": principal,
                          "intrinsics_format": "ndc_isotropic"},
            "meta": {},
        })
    return entries


# --- checks shared by the tests ---------------------------------------------------------------------


def project(points, camera):
    """``(N, 3)`` NDC x, y and depth of ``points`` ``(N, 3)`` seen by ``camera`` (batch ``()``)."""
    from cdm.cameras import Cameras, project_points

    one = Cameras(camera.R[None], camera.T[None], camera.focal[None], camera.principal[None])
    return project_points(points[None], one)[0]


def mirrored(camera):
    """``camera`` with its view x axis flipped: a mirror image, what a wrong handedness gives."""
    import torch

    from cdm.cameras import Cameras

    flip = torch.tensor([-1.0, 1.0, 1.0])
    return Cameras(camera.R * flip, camera.T * flip, camera.focal, camera.principal)


# Negative controls of cdm.data.checks.check_masks: each is a bug the check must catch.


def unmapped_frame(points, camera):
    """The cloud left in PC15k's v2 frame (a loader without BDM's ``transform_v2_to_v1``): on the cloud in
    BDM's frame the same involution, up to a shift of the frame's centre."""
    import torch

    return torch.from_numpy(v1_to_v2(points.numpy())).float(), camera


def mirrored_x(points, camera):
    """The camera mirrored in its view x axis (a handedness bug)."""
    return points, mirrored(camera)


def wrong_distance(points, camera):
    """The camera at the metadata's distance ratio without R2N2's ×1.75 (a distance-scale bug)."""
    from cdm.cameras import Cameras

    return points, Cameras(camera.R, camera.T / 1.75, camera.focal, camera.principal)


def mask_check_report(dataset, perturb=None):
    """``[MaskCheck]`` of every object of ``dataset`` (see :func:`cdm.data.checks.check_masks`)."""
    from cdm.data.checks import check_masks

    return [check_masks(dataset, i, perturb) for i in range(len(dataset))]


# --- estimated depth maps (priors.depth_source: maps) ---------------------------------------------


def ramp_depth(position: int, size: int = 16) -> np.ndarray:
    """``(size, size)`` float32 depths in (1, 3): a plane tilted in a direction set by the sequence
    ``position``, so a map read for the wrong view gives another depth prior (a shift would not: the
    prior is normalised per image)."""
    y, x = np.mgrid[0:size, 0:size] / (size - 1) - 0.5
    angle = 0.7 * position
    return (2.0 + math.cos(angle) * x + math.sin(angle) * y).astype(np.float32)


def write_depth_maps(folder: Path, cfg) -> None:
    """:func:`ramp_depth` as the estimated map of every input view of every object of ``cfg``'s two
    splits, in the ``priors.depth_maps`` layout ``<object_id>/<position>.npy``."""
    from cdm.data import build_dataset

    for split in ("train", "val"):
        ds = build_dataset(cfg, split)
        for index, ref in enumerate(ds.objects):
            (folder / ref.object_id).mkdir(parents=True, exist_ok=True)
            for position in ds.record(index).views.tolist():
                np.save(folder / ref.object_id / f"{position}.npy", ramp_depth(position))
