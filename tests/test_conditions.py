"""Extra condition views (``data.condition_views``, ``data.input_source``; supplementary Table 8)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cdm.cameras import look_at_cameras
from cdm.config import ConfigError, load_config, parse_override
from cdm.data import build_dataset
from cdm.data.condition_images import grey
from cdm.data.sample import collate
from cdm.data.views import render_view
from cdm.external_inputs import check_coverage, check_inputs
from cdm.model import CDMNetwork, project_conditioning
from cdm.model.conditioning import conditioning_channels, conditioning_map, project_views
from cdm.render import rasterize_points
from tests.conftest import tiny_config
from tests.input_fixtures import object_ids, write_condition_images

PC2 = {"priors.prior_3d": False, "priors.prior_2d": "none"}


def test_project_views_averages_over_the_views_that_see_a_point():
    s, n = 16, 60
    g = torch.Generator().manual_seed(0)
    points = (torch.rand(1, n, 3, generator=g) * 2 - 1) * 0.8
    maps = torch.randn(1, 2, 4, s, s, generator=g)
    cams = look_at_cameras(torch.tensor([[10.0, 30.0]]), torch.tensor([[0.0, 120.0]]), torch.tensor([[3.0, 3.0]]))
    got = project_views(maps, points, cams, torch.tensor([[True, True]]), 0.05)[0]
    flat = cams.flatten()
    seen, gathered = [], []
    for v in range(2):
        cam = flat[v : v + 1]
        seen.append(rasterize_points(points, cam, s, 0.05).visible[0])
        gathered.append(project_conditioning(maps[:, v], points, cam, 0.05)[0])
    counts = seen[0].int() + seen[1].int()
    assert (counts == 1).any() and (counts == 2).any() and (counts == 0).any()
    for i in range(n):  # the naive reference: the mean over the views whose z-buffer keeps point i
        views = [v for v in range(2) if seen[v][i]]
        expected = sum((gathered[v][i] for v in views), torch.zeros(4)) / max(1, len(views))
        assert torch.allclose(got[i], expected, atol=1e-6), i
    only_first = project_views(maps, points, cams, torch.tensor([[True, False]]), 0.05)[0]
    assert torch.allclose(only_first, gathered[0])  # one valid view = plain PC² projection


def test_gt_condition_views_are_renderings_from_turned_cameras(tmp_path):
    cfg = tiny_config(tmp_path, **PC2, **{"data.condition_views": 3})
    ds = build_dataset(cfg, "train")
    sample = ds.sample(1, view_round=2)
    c = sample.conditions
    assert c.image.shape == (3, 3, 32, 32) and c.mask.shape == (3, 1, 32, 32) and c.prior_2d.shape == (3, 0, 32, 32)
    assert c.valid.all() and c.camera.batch_shape == (3,)
    view = ds.drawn_view(1, 2)
    for j in range(1, 4):
        shot = render_view(ds.surface(1), view._replace(azim=view.azim + 90.0 * j), 32, 1)
        assert torch.equal(c.image[j - 1], shot.image) and torch.equal(c.camera.R[j - 1], shot.camera.R)
    # Camera centres (-T R^T) turn by 90° about +Y, at the input's distance.
    centres = [(-cam.T @ cam.R.T) for cam in [sample.camera, *[c.camera[j] for j in range(3)]]]
    for j in range(1, 4):
        cos = torch.dot(centres[0][[0, 2]], centres[j][[0, 2]]) / (
            centres[0][[0, 2]].norm() * centres[j][[0, 2]].norm()
        )
        assert cos == pytest.approx(np.cos(np.radians(90.0 * j)), abs=1e-4)
    assert build_dataset(cfg, "val").sample(0).conditions is None  # sampling sees the input only
    plain = build_dataset(tiny_config(tmp_path, **PC2), "train").sample(1, view_round=2)
    assert plain.conditions is None and torch.equal(plain.image, sample.image)  # extra views leave the input alone


def test_random_count_and_folder_images(tmp_path):
    base = tiny_config(tmp_path, **PC2)
    ids = object_ids(base)
    write_condition_images(tmp_path / "gen", ids, views=3, rounds=2)
    common = {**PC2, "data.condition_views": 3, "data.condition_folder": str(tmp_path / "gen")}
    counts = {int(build_dataset(tiny_config(tmp_path, **common, **{"data.condition_views_random": True}), "train")
                  .sample(i, r).conditions.valid.sum()) for i in range(4) for r in range(4)}
    assert counts <= {1, 2, 3} and len(counts) > 1
    folder = build_dataset(tiny_config(tmp_path, **common, **{"data.condition_source": "folder"}), "train")
    s = folder.sample(0, view_round=3)  # round 3 of 2 generated rounds reads round 1
    import cv2

    for v in range(1, 4):
        bgr = cv2.imread(str(tmp_path / "gen" / ids[0] / "1" / f"{v}.png"))
        assert torch.allclose(
            s.conditions.image[v - 1][:, 5, 5], torch.from_numpy(bgr[5, 5, ::-1].copy()).float() / 255
        )
    grey_in = build_dataset(tiny_config(tmp_path, **PC2, **{"data.input_source": "folder", "data.condition_grey": True,
                                                           "data.condition_folder": str(tmp_path / "gen")}), "val")
    image = grey_in.sample(0).image
    rgb = (
        torch.from_numpy(
            cv2.imread(str(tmp_path / "gen" / grey_in.objects[0].object_id / "0" / "0.png"))[5, 5, ::-1].copy()
        ).float()
        / 255
    )
    assert torch.allclose(
        image[:, 5, 5], torch.full((3,), float(0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2])), atol=1e-6
    )
    assert torch.allclose(
        grey(torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1).expand(3, 2, 2))[:, 0, 0], torch.full((3,), 0.299)
    )


def test_network_projects_condition_views_in_training_only(tmp_path):
    cfg = tiny_config(tmp_path, **PC2, **{"data.condition_views": 3})
    torch.manual_seed(0)
    net = CDMNetwork(cfg.model, 0)
    batch = collate([build_dataset(cfg, "train").sample(i) for i in range(2)])
    ctx = net.encode(batch)
    assert ctx.views.shape == (2, 3, 8 + 5, 32, 32) and ctx.view_valid.shape == (2, 3)
    t = torch.tensor([4, 9])
    with_views = net(batch.points, t, ctx, batch.camera)
    without = net(batch.points, t, ctx._replace(views=None, view_cameras=None, view_valid=None), batch.camera)
    assert not torch.allclose(with_views, without)  # back-facing points of the input view get features
    invalid = ctx._replace(view_valid=torch.zeros_like(ctx.view_valid))
    assert torch.allclose(net(batch.points, t, invalid, batch.camera), without, atol=1e-6)


def test_without_mask_channels_no_mask_reaches_the_points(tmp_path):
    """BDM's ShapeNet conditioning (``model.mask_channels: false``): features, 2D prior and RGB only."""
    g = torch.Generator().manual_seed(0)
    features, prior, image = (torch.rand(2, c, 8, 8, generator=g) for c in (4, 1, 3))
    mask = (torch.rand(2, 1, 8, 8, generator=g) > 0.5).float()
    full, bare = (
        conditioning_map(features, prior, image, mask, True),
        conditioning_map(features, prior, image, mask, False),
    )
    assert (
        (conditioning_channels(4, 1, True), conditioning_channels(4, 1, False))
        == (full.shape[1], bare.shape[1])
        == (10, 8)
    )
    assert torch.equal(bare, full[:, :8]) and torch.equal(
        bare, conditioning_map(features, prior, image, 1 - mask, False)
    )
    cfg = tiny_config(tmp_path, **PC2, **{"model.mask_channels": False})
    net = CDMNetwork(cfg.model, 0)
    batch = collate([build_dataset(cfg, "train").sample(i) for i in range(2)])
    assert net.encode(batch).pixel.shape == (2, conditioning_channels(0, 0, False), 32, 32)
    assert net(batch.points, torch.tensor([4, 9]), net.encode(batch), batch.camera).shape == batch.points.shape


def test_bad_condition_inputs_name_the_field(tmp_path):
    base = tiny_config(tmp_path, **PC2)
    ids = object_ids(base)
    write_condition_images(tmp_path / "gen", ids[1:], views=3)
    cfg = tiny_config(
        tmp_path, **PC2, **{"data.input_source": "folder", "data.condition_folder": str(tmp_path / "gen")}
    )
    with pytest.raises(ValueError, match=rf"data.condition_folder: no images for object id '{ids[0]}' \(1 of"):
        check_coverage(cfg, (build_dataset(cfg, "train"), build_dataset(cfg, "val")))
    missing = tiny_config(
        tmp_path, **PC2, **{"data.input_source": "folder", "data.condition_folder": str(tmp_path / "no")}
    )
    with pytest.raises(ValueError, match="data.condition_folder: .*no does not exist"):
        check_inputs(missing)
    with pytest.raises(ConfigError, match="data.condition_folder is required"):
        tiny_config(tmp_path, **{"data.input_source": "folder"})
    (tmp_path / "gen" / ids[1] / "0" / "2.png").write_bytes(b"not a png")
    folder = tiny_config(tmp_path, **PC2, **{"data.condition_views": 3, "data.condition_source": "folder",
                                             "data.condition_folder": str(tmp_path / "gen")})
    with pytest.raises(ValueError, match=r"data.condition_folder: cannot read .*2.png as an image"):
        build_dataset(folder, "train").sample(
            next(i for i, o in enumerate(build_dataset(folder, "train").objects) if o.object_id == ids[1])
        )


def test_captured_condition_views_are_other_input_views_and_folder_images_go_by_position(tmp_path):
    import cv2

    from tests.datasets_fixtures import make_co3d

    root = make_co3d(tmp_path / "co3d", categories=("teddybear",)).root
    common = {"data.kind": "co3d", "data.root": str(root), "data.categories": ["teddybear"], "data.image_size": 32,
              "data.num_points": 256, **PC2}
    gt = build_dataset(tiny_config(tmp_path, **common, **{"data.condition_views": 2}), "train")
    plain = build_dataset(tiny_config(tmp_path, **common), "train")
    surface = gt.surface(0)
    n = len(surface.views)
    sample = gt.sample(0, view_round=1)
    choice = next(c for c in range(n) if torch.equal(plain._view_tensors(0, c)[1], sample.image))
    for j, c in enumerate((choice + round(i * n / 3)) % n for i in (1, 2)):
        v, image, mask, _ = plain._view_tensors(0, c)
        assert torch.equal(sample.conditions.image[j], image) and torch.equal(sample.conditions.mask[j], mask)
        assert torch.equal(sample.conditions.camera.R[j], v.camera.R)
    assert torch.equal(plain.sample(0, view_round=1).image, sample.image) and plain.sample(0, 1).conditions is None
    folder = tmp_path / "gen"
    for ds in (plain, build_dataset(tiny_config(tmp_path, **common), "val")):
        for i, ref in enumerate(ds.objects):
            (folder / ref.object_id).mkdir(parents=True, exist_ok=True)
            for position in ds.surface(i).views.tolist():
                cv2.imwrite(
                    str(folder / ref.object_id / f"{position}.png"),
                    np.full((20, 20, 3), (position * 9) % 256, np.uint8),
                )
    cfg = tiny_config(tmp_path, **common, **{"data.input_source": "folder", "data.condition_folder": str(folder)})
    check_coverage(cfg, (build_dataset(cfg, "train"), build_dataset(cfg, "val")))
    val = build_dataset(cfg, "val")
    position = int(val.surface(0).views[0])
    assert torch.allclose(val.sample(0).image, torch.full((3, 32, 32), ((position * 9) % 256) / 255.0))


def test_export_views_writes_what_the_model_sees_under_the_input_names(tmp_path):
    import json

    import cv2

    from cdm.tools.export_views import main as export_main
    from tests.datasets_fixtures import make_co3d

    sets = ["data.categories=[mug]", "data.train_objects=1", "data.val_objects=1", "data.image_size=32",
            "data.condition_views=1", "data.num_points=128", "priors.prior_3d=false", "priors.prior_2d=none"]
    assert (
        export_main(["--out", str(tmp_path / "views"), "--rounds", "2", *(a for s in sets for a in ("--set", s))]) == 0
    )
    cfg = tiny_config(tmp_path, **{"data.categories": ["mug"], "data.train_objects": 1, "data.val_objects": 1,
                                   "data.condition_views": 1, **PC2})
    ds = build_dataset(cfg, "train")
    folder = tmp_path / "views" / ds.objects[0].object_id
    assert json.loads((tmp_path / "views" / "objects.json").read_text())[ds.objects[0].object_id] == "mug"
    for r in (0, 1):
        sample = ds.sample(0, r)
        png = (
            torch.from_numpy(cv2.imread(str(folder / str(r) / "0.png"))[..., ::-1].copy()).permute(2, 0, 1).float()
            / 255
        )
        assert (png - sample.image).abs().max() <= 0.5 / 255 + 1e-6  # the input image, 8-bit
        extra = (
            torch.from_numpy(cv2.imread(str(folder / str(r) / "1.png"))[..., ::-1].copy()).permute(2, 0, 1).float()
            / 255
        )
        assert (extra - sample.conditions.image[0]).abs().max() <= 0.5 / 255 + 1e-6  # condition view 1
        assert (
            np.load(folder / str(r) / "1.depth.npy").shape == (32, 32) and (folder / str(r) / "1.points.png").is_file()
        )
    assert not (folder / "2").exists()
    root = make_co3d(tmp_path / "co3d", categories=("teddybear",)).root
    co3d = ["data.kind=co3d", f"data.root={root}", "data.categories=[teddybear]", "data.image_size=32"]
    assert export_main(["--out", str(tmp_path / "crops"), *(a for s in co3d for a in ("--set", s))]) == 0
    cap = build_dataset(load_config(None, dict(parse_override(s) for s in co3d)), "val")
    position = int(cap.surface(0).views[0])
    crop = cv2.imread(str(tmp_path / "crops" / cap.objects[0].object_id / f"{position}.png"))[..., ::-1]
    assert np.array_equal(crop, cap.view(0, 0).image)
