"""Data sets: procedural shapes, mesh folders, the shared view renderer and the registry."""

from __future__ import annotations

import math
import typing

import numpy as np
import pytest
import torch
import trimesh

from cdm.cameras import ndc_to_pixel, project_points
from cdm.config import Config, ConfigError, DataKind, load_config
from cdm.data import DATASETS, build_dataset, collate, list_categories
from cdm.data.procedural_shapes import CATEGORIES, make_shape
from cdm.data.views import RASTER_RADIUS_PX, Shape, View, draw_palette, render_view, sample_surface
from cdm.normalise import IDENTITY, Frame


def _cfg(**overrides) -> Config:
    small = {
        "data.image_size": 32,
        "data.num_points": 256,
        "data.train_objects": 3,
        "data.val_objects": 2,
        "priors.num_views": 4,
    }
    return load_config(None, {**small, **overrides})


def _same(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def _tensors(s) -> list[torch.Tensor]:
    cams = [s.camera.R, s.camera.T, s.camera.focal, s.view_cameras.R, s.view_cameras.focal]
    return [s.image, s.mask, s.depth, s.prior_2d, s.points, *cams]


# --- procedural -----------------------------------------------------------------------------------


def test_the_registry_holds_every_kind_the_config_accepts_and_the_config_refuses_others():
    assert sorted(DATASETS) == sorted(typing.get_args(DataKind))
    assert all(cls.kind == kind for kind, cls in DATASETS.items())
    allowed = "'procedural', 'meshes', 'shapenet_r2n2' or 'co3d'"
    with pytest.raises(ConfigError, match=f"data.kind: Input should be {allowed}"):
        load_config(None, {"data.kind": "pix3d"})


def test_eight_categories_listed():
    assert len(CATEGORIES) == 8 and list(CATEGORIES) == sorted(CATEGORIES)
    assert list_categories(_cfg()) == CATEGORIES
    assert list_categories(_cfg(**{"data.categories": ["mug", "chair"]})) == ("mug", "chair")


def test_same_seed_same_samples_other_seed_differs():
    a, b = build_dataset(_cfg(), "train"), build_dataset(_cfg(), "train")
    other = build_dataset(_cfg(**{"data.seed": 1}), "train")
    for i in (0, 5):
        assert _same(_tensors(a[i]), _tensors(b[i]))
        assert not torch.equal(a[i].points, other[i].points)
        assert a[i].object_id == other[i].object_id


def test_make_shape_is_a_function_of_the_generator():
    for category in CATEGORIES:
        one = make_shape(category, np.random.default_rng(7))
        two = make_shape(category, np.random.default_rng(7))
        assert np.array_equal(one.mesh.vertices, two.mesh.vertices)
        assert len(one.material) == len(one.mesh.faces)


def test_every_category_gives_clouds_in_its_frame_at_their_own_size():
    ds = build_dataset(_cfg(**{"data.val_objects": 3}), "val")
    assert len(ds) == 8 * 3
    extents: dict[str, list[float]] = {}
    for i in range(len(ds)):
        s = ds[i]
        assert s.points.shape == (256, 3) and s.points.dtype == torch.float32
        assert s.points.abs().max() <= 1.0, s.object_id
        extents.setdefault(s.category, []).append(float((s.points.max(0).values - s.points.min(0).values).max()))
    assert set(extents) == set(CATEGORIES)
    # Not fitted per object: the largest extent differs between objects of a category (a per-object
    # box would give 2.0 to every one of them, up to sampling).
    for category, sizes in extents.items():
        assert max(sizes) - min(sizes) > 0.05 and min(sizes) < 1.9, (category, sizes)


def test_categories_interleave_so_prefixes_cover_all():
    ds = build_dataset(_cfg(), "train")
    assert [ref.category for ref in ds.objects[:8]] == list(CATEGORIES)
    assert ds.objects[8].object_id == "procedural/airplane/train/00001"


def test_shapes_vary_continuously_within_a_category():
    ds = build_dataset(_cfg(**{"data.train_objects": 6, "data.categories": ["chair", "bottle", "ring"]}), "train")
    for category in ("chair", "bottle", "ring"):
        extents = [
            tuple(ds.surface(i).cloud.max(0).values - ds.surface(i).cloud.min(0).values)
            for i in range(len(ds))
            if ds.objects[i].category == category
        ]
        assert len({tuple(round(float(e), 3) for e in ext) for ext in extents}) == 6


def test_train_and_val_never_share_an_object():
    cfg = _cfg()
    train, val = build_dataset(cfg, "train"), build_dataset(cfg, "val")
    train_ids = {ref.object_id for ref in train.objects}
    val_ids = {ref.object_id for ref in val.objects}
    assert train_ids.isdisjoint(val_ids) and len(train_ids) == 24 and len(val_ids) == 16
    # Same index, same category: the shapes themselves differ.
    assert not torch.equal(train.surface(0).cloud, val.surface(0).cloud)


def test_val_views_are_fixed_train_views_follow_the_round():
    cfg = _cfg()
    val, train = build_dataset(cfg, "val"), build_dataset(cfg, "train")
    first_val, first_train = val[3], train[3]
    val.set_epoch(5)
    train.set_epoch(5)
    assert _same(_tensors(val[3]), _tensors(first_val))
    moved = train[3]
    assert torch.equal(moved.points, first_train.points)
    assert not torch.equal(moved.camera.R, first_train.camera.R)
    assert _same(_tensors(train.sample(3, 0)), _tensors(first_train))


def test_image_mask_depth_agree():
    ds = build_dataset(_cfg(**{"data.image_size": 48}), "val")
    for i in range(8):
        s = ds[i]
        assert s.image.shape == (3, 48, 48) and s.mask.shape == (1, 48, 48) and s.depth.shape == (1, 48, 48)
        assert torch.equal(s.mask, (s.depth > 0).float())
        assert 0.02 < s.mask.mean() < 0.9
        assert s.image.min() >= 0 and s.image.max() <= 1
        background = s.image[:, s.mask[0] == 0]
        assert torch.equal(background, background[:, :1].expand_as(background)), "plain grey background"
        assert torch.all(background[0] == background[1])
        # Camera distance 3–4 and the object inside the unit cube: depth within dist ± sqrt(3).
        dist = s.camera.T.norm()
        fg = s.depth[s.mask > 0]
        assert fg.min() >= dist - math.sqrt(3) and fg.max() <= dist + math.sqrt(3)


def test_ground_truth_projects_into_the_mask_and_fits_every_view():
    ds = build_dataset(_cfg(**{"data.image_size": 64}), "val")
    for i in range(8):
        s = ds[i]
        cam = s.view_cameras[:1]
        ndc = project_points(s.points[None], cam)[0]
        col, row = ndc_to_pixel(ndc[:, :2], 64).round().long().unbind(-1)
        assert ((col >= 0) & (col < 64) & (row >= 0) & (row < 64)).all()
        inside = s.mask[0, row, col]
        assert inside.mean() > 0.97, (s.object_id, inside.mean())
        views = s.view_cameras
        ndc_all = project_points(s.points[None].expand(len(views), -1, -1), views)
        assert ndc_all[..., :2].abs().max() < 0.95  # fill is at most 0.9 of the half-frame


def test_prior_views_and_2d_prior_follow_config():
    s = build_dataset(_cfg(), "val")[0]
    assert s.view_cameras.batch_shape == (4,) and s.camera.batch_shape == ()
    assert torch.equal(s.view_cameras.R[0], s.camera.R) and torch.equal(s.view_cameras.T[0], s.camera.T)
    # Camera centres C = -T Rᵀ turn by 90° about +Y between the 4 views, at constant height and distance.
    centres = -(s.view_cameras.T[:, None, :] @ s.view_cameras.R.transpose(-1, -2))[:, 0]
    angles = torch.rad2deg(torch.atan2(centres[:, 0], centres[:, 2]))
    steps = angles.diff() % 360.0
    assert torch.allclose(steps, torch.full((3,), 90.0), atol=1e-3)
    assert torch.allclose(centres[:, 1], centres[:1, 1].expand(4), atol=1e-5)
    assert s.prior_2d.shape == (1, 32, 32)
    off = build_dataset(_cfg(**{"priors.prior_3d": False, "priors.prior_2d": "none"}), "val")[0]
    assert off.view_cameras.batch_shape == (1,) and off.prior_2d.shape == (0, 32, 32)
    depth = build_dataset(_cfg(**{"priors.prior_2d": "depth"}), "val")[0]
    assert depth.prior_2d.shape == (1, 32, 32) and depth.prior_2d.max() == 1.0  # nearest pixel
    assert (depth.prior_2d[depth.mask == 0] == 0).all()


def test_samples_collate_into_a_batch():
    ds = build_dataset(_cfg(), "train")
    batch = collate([ds[i] for i in range(3)])
    assert batch.image.shape == (3, 3, 32, 32) and batch.points.shape == (3, 256, 3)
    assert batch.view_cameras.batch_shape == (3, 4) and batch.category == tuple(CATEGORIES[:3])


def test_small_cache_evicts_without_changing_samples():
    cfg = _cfg()
    full, tiny = build_dataset(cfg, "train"), DATASETS["procedural"](cfg, "train", cache_bytes=1)
    for i in (0, 1, 2, 0):
        assert _same(_tensors(full[i]), _tensors(tiny[i]))
    assert len(tiny._cache) == 1


def test_unknown_or_repeated_procedural_category_is_named():
    with pytest.raises(
        ValueError, match=r"data\.categories: \['teapot'\] not in the procedural .* allowed: airplane, bottle"
    ):
        build_dataset(_cfg(**{"data.categories": ["teapot"]}), "train")
    with pytest.raises(ValueError, match=r"data\.categories: .* names a category twice"):
        list_categories(_cfg(**{"data.categories": ["mug", "mug"]}))
    with pytest.raises(ValueError, match="unknown procedural category 'teapot'"):
        make_shape("teapot", np.random.default_rng(0))


# --- the shared renderer on known geometry -----------------------------------------------------------


def test_sample_surface_maps_the_mesh_by_the_given_frame():
    box = trimesh.creation.box(extents=(2.0, 4.0, 6.0))
    box.apply_translation((5.0, -3.0, 1.0))
    palette = draw_palette(np.random.default_rng(0))
    frame = Frame((4.0, -3.0, 1.0), 0.25)  # not the box's own: its centre lands at x = 0.25
    surface = sample_surface(
        Shape(box, np.zeros(12, dtype=np.int64)), frame, 2000, 500, np.random.default_rng(0), palette
    )
    lo, hi = surface.cloud.min(0).values, surface.cloud.max(0).values
    assert torch.allclose(lo, torch.tensor([0.0, -0.5, -0.75]), atol=1e-5)
    assert torch.allclose(hi, torch.tensor([0.5, 0.5, 0.75]), atol=1e-5)
    # Every sample lies on a face of the box [0, 0.5]×[-0.5, 0.5]×[-0.75, 0.75]: one coordinate at its bound.
    centred = surface.points - torch.tensor([0.25, 0.0, 0.0])
    on_face = (centred.abs() - torch.tensor([0.25, 0.5, 0.75])).abs().min(-1).values
    assert on_face.max() < 1e-5 and surface.normals.norm(dim=-1).allclose(torch.ones(500))


def test_sphere_depth_and_shading():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    white = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    shape = Shape(sphere, np.zeros(len(sphere.faces), dtype=np.int64))
    surface = sample_surface(shape, IDENTITY, 64, 20000, np.random.default_rng(1), white)
    light = torch.tensor([0.0, 0.0, -1.0])  # from the camera
    view = View(elev=20.0, azim=30.0, dist=3.5, fill=0.8, light=light, ambient=0.2, background=0.5)
    r = render_view(surface, view, 65, 1)
    centre = 32
    assert r.depth[0, centre, centre] == pytest.approx(2.5, abs=0.01)
    # Lit head-on: the centre is brightest (ambient + diffuse ≈ 1), the rim darkest.
    assert r.image[0, centre, centre] == pytest.approx(1.0, abs=0.01)
    rim = r.image[0][(r.mask[0] > 0)].min()
    assert rim < 0.5 and (r.image[:, r.mask[0] == 0] == 0.5).all()
    # Silhouette radius: fill · half-frame (0.8 · 32.5 px) grown by the points' disc radius.
    radius_px = math.sqrt(r.mask.sum().item() / math.pi)
    assert radius_px == pytest.approx(0.8 * 32.5 + RASTER_RADIUS_PX, abs=0.5)


# --- mesh folders ------------------------------------------------------------------------------------


def _write_folder(root, per_category: int = 3):
    shapes = {
        "box": lambda k: trimesh.creation.box(extents=(1.0, 1.0 + k, 2.0)),
        "ball": lambda k: trimesh.creation.icosphere(subdivisions=2, radius=1.0 + k),
    }
    suffixes = (".obj", ".ply", ".stl", ".off")
    for category, make in shapes.items():
        (root / category).mkdir(parents=True)
        for k in range(per_category):
            make(0.1 * k).export(root / category / f"m{k}{suffixes[k % len(suffixes)]}")
    return root


def _mesh_cfg(root, **overrides) -> Config:
    return _cfg(**{"data.kind": "meshes", "data.root": str(root), **overrides})


def test_mesh_folder_categories_splits_and_samples(tmp_path):
    root = _write_folder(tmp_path / "meshes", per_category=12)
    cfg = _mesh_cfg(root)
    assert list_categories(cfg) == ("ball", "box")
    train, val = build_dataset(cfg, "train"), build_dataset(cfg, "val")
    assert len(train) + len(val) == 24
    train_ids, val_ids = {r.object_id for r in train.objects}, {r.object_id for r in val.objects}
    assert train_ids.isdisjoint(val_ids)
    assert {r.category for r in val.objects} == {"ball", "box"}  # 10 % rounded, at least one each
    assert "meshes/box/m0.obj" in train_ids | val_ids
    assert {p.rsplit(".", 1)[1] for p in train_ids} == {"obj", "ply", "stl", "off"}
    again = build_dataset(cfg, "val")
    for i in range(len(val)):
        s = val[i]
        assert _same(_tensors(s), _tensors(again[i]))
        assert s.points.shape == (256, 3) and s.points.abs().max() <= 1.0
        assert torch.equal(s.mask, (s.depth > 0).float()) and s.mask.sum() > 0
    # The box category's frame is the union box of its training meshes (extents (1, 1 + 0.1k, 2), all
    # centred): half-extents (0.5, (1 + 0.1 k_max)/2, 1), the largest 1.0 or above it.
    k_max = max(int(r.object_id.rsplit("/m", 1)[1].split(".")[0]) for r in train.objects if r.category == "box")
    scale = 1.0 / max(1.0, (1.0 + 0.1 * k_max) / 2)
    box = next(
        d.surface(i) for d in (train, val) for i in range(len(d)) if d.objects[i].object_id.endswith("box/m0.obj")
    )
    assert torch.allclose(box.cloud.abs().max(0).values, torch.tensor([0.5, 0.5, 1.0]) * scale, atol=1e-4)


def test_mesh_folder_merges_scenes(tmp_path):
    root = tmp_path / "scenes"
    (root / "pair").mkdir(parents=True)
    for k in range(2):
        left = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        right = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        right.apply_translation((3.0 + k, 0.0, 0.0))
        trimesh.Scene([left, right]).export(root / "pair" / f"s{k}.glb")
    ds = build_dataset(_mesh_cfg(root, **{"data.categories": ["pair"]}), "train")
    cloud = ds.surface(0).cloud
    # Both boxes are present: x covers [-1, 1] with a gap in the middle.
    assert cloud[:, 0].min() < -0.95 and cloud[:, 0].max() > 0.95
    assert (cloud[:, 0].abs() < 0.2).sum() == 0


@pytest.mark.parametrize(
    "case", ["unset", "missing", "empty", "no_meshes", "corrupt", "point_cloud", "too_few", "unknown_category"]
)
def test_mesh_folder_errors_name_the_problem(tmp_path, case):
    root = tmp_path / "data"
    expected = {
        "unset": r"data\.root must name a folder",
        "missing": r"data\.root: .*data is not a readable folder",
        "empty": r"data\.root: .*no category sub-folder",
        "no_meshes": r"data\.root: .*no category sub-folder",
        "corrupt": r"data\.root: cannot read mesh .*box[/\\]broken\.ply",
        "point_cloud": r"data\.root: .*box[/\\]cloud\.ply holds no triangles",
        "too_few": r"data\.root: category folder .*solo has 1 mesh",
        "unknown_category": r"data\.categories: \['cup'\] not in data\.root .*data; allowed: ball, box",
    }[case]
    overrides = {}
    if case == "empty":
        root.mkdir()
    elif case == "no_meshes":
        (root / "notes").mkdir(parents=True)
        (root / "notes" / "readme.txt").write_text("not a mesh")
    elif case != "missing" and case != "unset":
        _write_folder(root, per_category=3)
    if case == "corrupt":
        (root / "box" / "broken.ply").write_bytes(b"garbage\x00\x01 not a mesh")
    elif case == "point_cloud":
        trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(root / "box" / "cloud.ply")
    elif case == "too_few":
        (root / "solo").mkdir()
        trimesh.creation.box().export(root / "solo" / "only.obj")
    elif case == "unknown_category":
        overrides["data.categories"] = ["cup"]
    cfg = _cfg(**{"data.kind": "meshes"}) if case == "unset" else _mesh_cfg(root, **overrides)
    with pytest.raises(ValueError, match=expected):
        # The bad file sits in one of the two splits (by its name's hash); building both must fail.
        build_dataset(cfg, "train")
        build_dataset(cfg, "val")


def test_input_view_does_not_depend_on_the_number_of_prior_views(tmp_path):
    """Ablations over H or prior_3d must compare the same input images."""
    base = {"data": {"image_size": 32, "num_points": 64, "train_objects": 2, "val_objects": 1, "categories": ["chair"]}}
    images = []
    for priors in ({"num_views": 10}, {"num_views": 3}, {"prior_3d": False, "num_views": 0}):
        cfg = load_config({**base, "priors": priors})
        sample = build_dataset(cfg, "val")[0]
        images.append(sample.image)
        assert sample.view_cameras.T.shape[0] == max(1, priors["num_views"])
    assert torch.equal(images[0], images[1]) and torch.equal(images[0], images[2])


# --- the mask check on rendered kinds ----------------------------------------------------------------


def _ell_folder(root):
    """Mesh folder of asymmetric L shapes (a mirror of one is not itself)."""
    for category in ("ell", "step"):
        (root / category).mkdir(parents=True)
        for k in range(6):
            a = trimesh.creation.box(extents=[1.0, 0.2 + 0.05 * k, 0.5])
            b = trimesh.creation.box(extents=[0.25, 0.8, 0.5])
            b.apply_translation([0.375, 0.5, 0.1 * k if category == "step" else 0.0])
            trimesh.util.concatenate([a, b]).export(root / category / f"m{k}.obj")
    return root


@pytest.mark.parametrize("kind", ["procedural", "meshes"])
def test_mask_check_passes_on_rendered_kinds_and_its_negative_controls_fail(kind, tmp_path):
    from tests.datasets_fixtures import mask_check_report, mirrored_x, wrong_distance

    extra = {"data.kind": "meshes", "data.root": str(_ell_folder(tmp_path / "m"))} if kind == "meshes" else {}
    cfg = _cfg(**{"data.image_size": 64, "data.num_points": 512, **extra})
    for split in ("train", "val"):
        ds = build_dataset(cfg, split)
        checks = mask_check_report(ds)
        assert all(c.passed for c in checks) and min(float(c.fractions.min()) for c in checks) > 0.99
        assert all(len(c.fractions) == (3 if split == "train" else 1) for c in checks)
        assert not any(c.passed for c in mask_check_report(ds, wrong_distance))
        mirror = mask_check_report(ds, mirrored_x)
        # Procedural boxes, spheres and tori are mirror-symmetric and pass mirrored; the rest must not.
        assert not all(c.passed for c in mirror) and np.mean([float(c.fractions.mean()) for c in mirror]) < 0.9
        if kind == "meshes":
            assert not any(c.passed for c in mirror)
