"""Co3D v2 on a small tree in the published layout (gzipped annotations, JPEG, 16-bit depth, PLY)."""

from __future__ import annotations

import gzip
import json
import shutil

import numpy as np
import pytest
import torch

from cdm.__main__ import main
from cdm.cameras import select_sequence_views
from cdm.config import load_config
from cdm.data import build_dataset, list_categories
from cdm.data.co3d import PRIOR_FILL
from cdm.data.checks import inside_mask
from tests.datasets_fixtures import make_co3d, mask_check_report, mirrored, mirrored_x, project, wrong_distance


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return make_co3d(tmp_path_factory.mktemp("co3d"))


def _cfg(root, **overrides):
    return load_config(None, {"data.kind": "co3d", "data.root": str(root), "data.image_size": 64, "data.num_points": 2048,
                              "priors.num_views": 4, **overrides})


def test_samples_have_the_right_shapes_and_scales(tree):
    ds = build_dataset(_cfg(tree.root), "val")
    for i in range(len(ds)):
        s = ds[i]
        assert s.image.shape == (3, 64, 64) and 0 <= s.image.min() and s.image.max() <= 1
        assert s.mask.shape == (1, 64, 64) and set(s.mask.unique().tolist()) == {0.0, 1.0}
        assert 0.1 < s.mask.mean() < 0.7  # the crop keeps a margin around the object
        assert s.depth.shape == (1, 64, 64)
        assert torch.all((s.depth > 0) <= (s.mask > 0)) and (s.depth[s.mask > 0] > 0).float().mean() > 0.95
        assert s.points.shape == (2048, 3) and s.points.abs().max() <= 1.0
        cloud = ds.record(i).cloud
        lo, hi = cloud.min(0).values, cloud.max(0).values
        # The PLY's stray points (40 units away) are dropped: the object alone spans [-1, 1].
        assert len(cloud) == 6000 and (hi - lo).max() == pytest.approx(2.0) and ((hi + lo) / 2).abs().max() < 1e-6
        assert s.view_cameras.batch_shape == (4,)


def test_depth_is_float16_bits_times_scale_adjustment_in_normalised_units(tree):
    ds = build_dataset(_cfg(tree.root), "train")
    for i in range(len(ds)):
        s = ds.sample(i, 0)
        ndc = project(ds.record(i).cloud, s.camera)  # the whole cloud: a z-buffer as dense as the depth map
        size = 64
        col = ((1 - ndc[:, 0]) * size / 2 - 0.5).round().long()
        row = ((1 - ndc[:, 1]) * size / 2 - 0.5).round().long()
        nearest = torch.full((size * size,), float("inf")).scatter_reduce(0, row * size + col, ndc[:, 2], reduce="amin")
        nearest = nearest.view(size, size)
        both = torch.isfinite(nearest) & (s.depth[0] > 0)
        error = ((s.depth[0][both] - nearest[both]).abs() / nearest[both]).median()
        # Within 3 % (the fixture splats 1.2-px discs, a little nearer than a per-pixel minimum); a
        # missed scale_adjustment (0.8) or normalisation would be off by 25 % or more.
        assert both.sum() > 400 and error < 0.03, (s.object_id, float(error))


def test_ground_truth_projects_into_the_mask_and_a_mirror_does_not(tree):
    mirror = []
    for split in ("train", "val"):
        ds = build_dataset(_cfg(tree.root, **{"data.image_size": 96}), split)
        for i in range(len(ds)):
            for round_ in range(3):
                s = ds.sample(i, round_)
                assert inside_mask(s.points, s.camera, s.mask) >= 0.95, (s.object_id, round_)
                mirror.append(inside_mask(s.points, mirrored(s.camera), s.mask))
    assert np.mean(mirror) < 0.8


@pytest.mark.parametrize("split", ["train", "val"])
def test_mask_check_passes_on_every_view_and_its_negative_controls_fail(tree, split):
    ds = build_dataset(_cfg(tree.root, **{"data.image_size": 96}), split)
    checks = mask_check_report(ds)
    assert checks and all(c.passed for c in checks), [(c.object_id, c.fractions.min().item()) for c in checks]
    for control in (mirrored_x, wrong_distance):
        bad = mask_check_report(ds, control)
        assert not any(c.passed for c in bad), control.__name__


def test_prior_views_are_evenly_spaced_frames_of_the_sequence(tree):
    ds = build_dataset(_cfg(tree.root, **{"priors.num_views": 3}), "train")
    record = ds.record(0)
    assert len(record.sequence) == 6 and record.views.tolist() == list(range(6))  # train lists every frame
    for round_ in range(4):
        s = ds.sample(0, round_)
        start = int(torch.nonzero((record.sequence.R == s.camera.R).all(-1).all(-1))[0])
        positions = select_sequence_views(6, start, 3)
        assert positions == [start, (start + 2) % 6, (start + 4) % 6]
        assert torch.allclose(s.view_cameras.R[1:], record.sequence.R[positions[1:]])
        for k in range(1, 3):  # the fitted square crop: the cloud reaches PRIOR_FILL of the half-frame
            reach = project(s.points, s.view_cameras[k])[:, :2].abs().max()
            assert PRIOR_FILL * 0.9 < reach <= PRIOR_FILL + 1e-4


def test_split_filtering_follows_the_fewview_dev_set_list(tree):
    def sequences(split, **overrides):
        return {ref.object_id for ref in build_dataset(_cfg(tree.root, **overrides), split).objects}

    for published, ours, overrides in (("train", "train", {}), ("val", "val", {}), ("test", "val", {"data.eval_split": "test"})):
        expected = {f"co3d/{c}/{s}" for c in tree.sequences for s in tree.sequences[c][published]}
        assert sequences(ours, **overrides) == expected
    assert not {f"co3d/{c}/{s}" for c, s in tree.no_cloud.items()} & sequences("train")  # no point cloud: skipped


def test_categories(tree):
    assert list_categories(_cfg(tree.root)) == ("hydrant", "teddybear")
    assert list_categories(_cfg(tree.root, **{"data.categories": ["teddybear"]})) == ("teddybear",)
    ds = build_dataset(_cfg(tree.root), "train")
    assert [ref.category for ref in ds.objects] == ["hydrant", "teddybear", "hydrant", "teddybear"]


def _prepare(root, out, *extra):
    return main(["prepare", "--data-kind", "co3d", "--root", str(root), "--out", str(out), "--image-size", "32", *extra])


@pytest.mark.parametrize("damage,needle", [
    ("frame_annotations", "teddybear/frame_annotations.jgz is missing"),
    ("set_list", "teddybear/set_lists/set_lists_fewview_dev.json is missing"),
    ("bad_gzip", "teddybear/sequence_annotations.jgz: Not a gzipped file"),
    ("unknown_category", "data.categories: ['bicycle'] not in"),
    ("missing_root", "does not exist"),
])
def test_cli_errors_exit_2_naming_the_path(tree, tmp_path, capsys, damage, needle):
    root = tmp_path / "co3d"
    shutil.copytree(tree.root, root)
    extra = []
    if damage == "frame_annotations":
        (root / "teddybear" / "frame_annotations.jgz").unlink()
    elif damage == "set_list":
        (root / "teddybear" / "set_lists" / "set_lists_fewview_dev.json").unlink()
    elif damage == "bad_gzip":
        (root / "teddybear" / "sequence_annotations.jgz").write_text("[]")
    elif damage == "unknown_category":
        extra = ["--set", "data.categories=[bicycle]"]
    else:
        shutil.rmtree(root)
    assert _prepare(root, tmp_path / "out", *extra) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and needle in err and str(root) in err
    assert not (tmp_path / "out").exists()


def test_corrupt_jpeg_exits_2_naming_it(tree, tmp_path, capsys):
    root = tmp_path / "co3d"
    shutil.copytree(tree.root, root)
    frames = json.loads(gzip.decompress((root / "hydrant" / "frame_annotations.jgz").read_bytes()))
    seq = tree.sequences["hydrant"]["val"][0]
    jpeg = root / next(f["image"]["path"] for f in frames if f["sequence_name"] == seq)
    jpeg.write_bytes(b"\xff\xd8 not really a JPEG")
    assert _prepare(root, tmp_path / "out", "--set", "data.categories=[hydrant]") == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith("error: data.root: cannot read image") and str(jpeg) in last
    assert not list((tmp_path / "out").rglob(".*tmp*"))
