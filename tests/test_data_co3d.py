"""Co3D v2 on a small tree in the published layout (gzipped annotations, JPEG, 16-bit depth, PLY)."""

from __future__ import annotations

import gzip
import hashlib
import json
import random
import shutil
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh

from cdm.__main__ import main
from cdm.cameras import select_sequence_views
from cdm.config import ConfigError, load_config
from cdm.data import build_dataset, list_categories
from cdm.data.checks import inside_mask
from cdm.data.co3d import centred_box, crop_camera
from cdm.data.co3d_annotations import load_category
from cdm.data.co3d_lists import EXCLUDE_SEQUENCE, LOW_QUALITY_SEQUENCE, excluded_sequences
from sweeps import run
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from tests.datasets_fixtures import (
    make_co3d,
    mask_check_report,
    mirrored,
    mirrored_x,
    project,
    wrong_distance,
)
from tests.input_fixtures import paper_inputs


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return make_co3d(tmp_path_factory.mktemp("co3d"))


def _cfg(root, **overrides):
    return load_config(
        None,
        {
            "data.kind": "co3d",
            "data.root": str(root),
            "data.image_size": 64,
            "data.num_points": 2048,
            "priors.num_views": 4,
            **overrides,
        },
    )


def test_samples_have_the_right_shapes_and_scales(tree):
    ds = build_dataset(_cfg(tree.root), "val")
    for i in range(len(ds)):
        s = ds[i]
        assert s.image.shape == (3, 64, 64) and 0 <= s.image.min() and s.image.max() <= 1
        assert s.mask.shape == (1, 64, 64) and set(s.mask.unique().tolist()) == {0.0, 1.0}
        assert 0.1 < s.mask.mean() < 0.7  # the crop keeps a margin around the object
        assert s.depth.shape == (1, 64, 64)
        assert torch.all((s.depth > 0) <= (s.mask > 0)) and (s.depth[s.mask > 0] > 0).float().mean() > 0.95
        assert s.points.shape == (2048, 3)
        cloud = ds.record(i).cloud
        # PC²'s frame: the PLY's own world units, nothing fitted; its stray points (40 units away) dropped.
        published = np.asarray(
            trimesh.load(tree.root / f"{ds.objects[i].object_id.split('/', 1)[1]}/pointcloud.ply").vertices
        )
        assert len(cloud) == 6000 and torch.equal(cloud, torch.from_numpy(published[:6000]).float())
        assert s.view_cameras.batch_shape == (4,)


def test_depth_is_float16_bits_times_scale_adjustment_in_world_units(tree):
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
        frames = load_category(tree.root / ds.objects[0].category).frames[ds.objects[0].object_id.rsplit("/", 1)[1]]
        for k in range(1, 3):  # the frame's centred square crop, from the annotation alone; the object in view
            focal, principal = crop_camera(frames[positions[k]], centred_box(frames[positions[k]]))
            assert float(s.view_cameras.focal[k]) == pytest.approx(focal)
            assert s.view_cameras.principal[k].tolist() == pytest.approx(list(principal))
            assert project(s.points, s.view_cameras[k])[:, :2].abs().max() < 1.0


def test_split_filtering_follows_the_fewview_dev_set_list(tree):
    def sequences(split, **overrides):
        return {ref.object_id for ref in build_dataset(_cfg(tree.root, **overrides), split).objects}

    for published, ours, overrides in (
        ("train", "train", {}),
        ("val", "val", {}),
        ("test", "val", {"data.eval_split": "test"}),
    ):
        expected = {f"co3d/{c}/{s}" for c in tree.sequences for s in tree.sequences[c][published]}
        assert sequences(ours, **overrides) == expected
    assert not {f"co3d/{c}/{s}" for c, s in tree.no_cloud.items()} & sequences("train")  # no point cloud: skipped


def test_categories(tree):
    assert list_categories(_cfg(tree.root)) == ("hydrant", "teddybear")
    assert list_categories(_cfg(tree.root, **{"data.categories": ["teddybear"]})) == ("teddybear",)
    ds = build_dataset(_cfg(tree.root), "train")
    assert [ref.category for ref in ds.objects] == ["hydrant", "teddybear", "hydrant", "teddybear"]


def _prepare(root, out, *extra):
    return main(
        ["prepare", "--set", "data.kind=co3d", "--root", str(root), "--out", str(out), "--set", "data.image_size=32",
         *extra]
    )


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


# --- PC²'s protocol: data.exclude_sequences, data.frames_per_sequence, data.mask_rgb, data.drop_outliers ---


def test_pc2_lists_are_copied_whole():
    # Sizes and the first and last entries of each list in PC²'s experiments/dataset/exclude_sequence.py.
    assert (
        len(EXCLUDE_SEQUENCE["hydrant"]),
        len(LOW_QUALITY_SEQUENCE["hydrant"]),
        len(LOW_QUALITY_SEQUENCE["teddybear"]),
    ) == (31, 42, 295)
    assert {"250_26810_55497", "613_98242_196036"} <= EXCLUDE_SEQUENCE["hydrant"]
    assert {"469_66175_130221", "590_88831_175196"} <= LOW_QUALITY_SEQUENCE["hydrant"]
    assert {"393_48310_95677", "341_35504_65289"} <= LOW_QUALITY_SEQUENCE["teddybear"]
    assert (
        len(excluded_sequences("hydrant")),
        len(excluded_sequences("teddybear")),
        excluded_sequences("toytruck"),
    ) == (73, 295, frozenset())


def test_listed_sequences_leave_every_split_of_their_category_only(tmp_path):
    hydrant_bad, teddybear_bad = "250_26810_55497", "393_48310_95677"  # on hydrant's list / on teddybear's
    tree = make_co3d(tmp_path, frames=3, splits={"train": 2, "val": 2, "test": 0},
                     sequence_names={"train": [hydrant_bad], "val": [teddybear_bad]})  # both names in both categories
    for split, listed in (("train", f"co3d/hydrant/{hydrant_bad}"), ("val", f"co3d/teddybear/{teddybear_bad}")):
        every = {ref.object_id for ref in build_dataset(_cfg(tree.root), split).objects}
        kept = {
            ref.object_id for ref in build_dataset(_cfg(tree.root, **{"data.exclude_sequences": True}), split).objects
        }
        assert len(every) == 4 and listed in every and kept == every - {listed}


def _pytorch3d_kept(root: Path, category: str, count: int) -> dict[str, set[int]]:
    """Frame numbers per sequence that PyTorch3D 0.7.3's ``JsonIndexDataset._filter_db`` keeps with PC²'s
    ``remove_empty_masks=True, n_frames_per_sequence=count``, written as there: one list of the category's
    frames in file order, indices grouped by sequence, each group shuffled by its seeded ``random.Random``."""
    frames = json.loads(gzip.decompress((root / category / "frame_annotations.jgz").read_bytes()))
    frames = [f for f in frames if f["mask"]["mass"] > 1]
    seq_to_idx = defaultdict(list)
    for idx, f in enumerate(frames):
        seq_to_idx[f["sequence_name"]].append(idx)
    keep_idx = []
    for seq, seq_indices in seq_to_idx.items():
        seed = int(hashlib.sha1(seq.encode("utf-8")).hexdigest(), 16) + 0
        keep_idx.extend(random.Random(seed).sample(sorted(seq_indices), len(seq_indices))[:count])
    kept = defaultdict(set)
    for i in keep_idx:
        kept[frames[i]["sequence_name"]].add(frames[i]["frame_number"])
    return kept


def _rewrite(path: Path, edit, gzipped: bool) -> None:
    raw = gzip.decompress(path.read_bytes()) if gzipped else path.read_bytes()
    text = json.dumps(edit(json.loads(raw))).encode()
    path.write_bytes(gzip.compress(text) if gzipped else text)


def test_frames_per_sequence_keeps_pytorch3ds_frames_before_the_set_lists(tmp_path):
    tree = make_co3d(tmp_path, categories=("teddybear",), frames=6, splits={"train": 3, "val": 2, "test": 0})
    folder = tree.root / "teddybear"
    # An empty mask on the frame PyTorch3D would otherwise keep: remove_empty_masks drops it first.
    empty_seq = tree.sequences["teddybear"]["val"][0]
    first_pick = _pytorch3d_kept(tree.root, "teddybear", 1)[empty_seq]

    def empty_mask(frames):
        for f in frames:
            if f["sequence_name"] == empty_seq and f["frame_number"] in first_pick:
                f["mask"]["mass"] = 0.0
        return frames

    _rewrite(folder / "frame_annotations.jgz", empty_mask, gzipped=True)
    # The frame kept of one train sequence listed under test instead: that sequence leaves train.
    moved_seq = tree.sequences["teddybear"]["train"][0]
    moved = _pytorch3d_kept(tree.root, "teddybear", 1)[moved_seq]

    def move(lists):
        lists["test"] += [e for e in lists["train"] if e[0] == moved_seq and e[1] in moved]
        lists["train"] = [e for e in lists["train"] if not (e[0] == moved_seq and e[1] in moved)]
        return lists

    _rewrite(folder / "set_lists" / "set_lists_fewview_dev.json", move, gzipped=False)
    assert _pytorch3d_kept(tree.root, "teddybear", 1)[empty_seq] != first_pick
    for count in (1, 2):
        want = _pytorch3d_kept(tree.root, "teddybear", count)
        for split in ("train", "val"):
            every = [ref.object_id for ref in build_dataset(_cfg(tree.root), split).objects]
            ds = build_dataset(_cfg(tree.root, **{"data.frames_per_sequence": count}), split)
            gone = {f"co3d/teddybear/{moved_seq}"} if split == "train" and count == 1 else set()
            assert [ref.object_id for ref in ds.objects] == [o for o in every if o not in gone]
            for i, ref in enumerate(ds.objects):
                seq = ref.object_id.rsplit("/", 1)[1]
                listed = want[seq] - (moved if seq == moved_seq else set())
                # The fixture numbers frames 1, 2, …: frame number = sequence position + 1.
                assert {p + 1 for p in ds.record(i).views.tolist()} == listed, (split, seq)


def test_masked_rgb_blacks_out_the_background_and_keeps_the_object(tree):
    plain = build_dataset(_cfg(tree.root), "val")
    masked = build_dataset(_cfg(tree.root, **{"data.mask_rgb": True}), "val")  # decoded in the same process
    kernel = np.ones((5, 5), np.uint8)
    for i in range(len(plain)):
        a, b = plain[i], masked[i]
        assert torch.equal(a.mask, b.mask) and torch.equal(a.points, b.points)
        fg = a.mask[0].numpy().astype(np.uint8)
        inside = torch.from_numpy(cv2.erode(fg, kernel) > 0)
        outside = torch.from_numpy(cv2.dilate(fg, kernel) == 0)
        assert inside.any() and outside.any()
        assert torch.equal(b.image[:, inside], a.image[:, inside])
        assert (
            torch.all(b.image[:, outside] == 0) and a.image[:, outside].mean() > 0.3
        )  # the fixture's background is noise


def test_drop_outliers_off_keeps_every_published_point(tree):
    kept = build_dataset(_cfg(tree.root, **{"data.drop_outliers": False}), "val")
    dropped = build_dataset(_cfg(tree.root), "val")
    for i in range(len(kept)):
        assert len(kept.record(i).cloud) == 6010 and len(dropped.record(i).cloud) == 6000  # the PLY's 10 stray points


PC2_PROTOCOL = {
    "data.exclude_sequences": True,
    "data.frames_per_sequence": 1,
    "data.mask_rgb": True,
    "data.drop_outliers": False,
}


def test_a_prepared_root_is_read_only_with_the_protocol_it_was_prepared_with(tree, tmp_path):
    assert (
        _prepare(tree.root, tmp_path / "pc2", *[a for k, v in PC2_PROTOCOL.items() for a in ("--set", f"{k}={v}")]) == 0
    )
    for split in ("train", "val"):
        raw = build_dataset(_cfg(tree.root, **{"data.image_size": 32}, **PC2_PROTOCOL), split)
        prepared = build_dataset(_cfg(tmp_path / "pc2", **{"data.image_size": 32}, **PC2_PROTOCOL), split)
        assert raw.objects == prepared.objects and prepared.prepared is not None
        for i in range(len(raw)):
            a, b = raw.sample(i, 1), prepared.sample(i, 1)
            assert (
                torch.equal(a.image, b.image) and torch.equal(a.points, b.points) and len(prepared.record(i).views) == 1
            )
    with pytest.raises(
        ValueError,
        match=r"data.mask_rgb: False, but .+ was prepared with True; prepare the published data "
        r"set again with --set data.mask_rgb=False",
    ):
        build_dataset(_cfg(tmp_path / "pc2", **{**PC2_PROTOCOL, "data.mask_rgb": False}), "val")
    assert _prepare(tree.root, tmp_path / "plain") == 0  # a root prepared with the defaults refuses PC²'s frames
    with pytest.raises(ValueError, match=r"data.exclude_sequences: True, but .+ was prepared with False"):
        build_dataset(_cfg(tmp_path / "plain", **PC2_PROTOCOL), "val")


@pytest.mark.parametrize(("kind", "field", "value"), [
    ("shapenet_r2n2", "data.mask_rgb", True), ("procedural", "data.frames_per_sequence", 1),
    ("meshes", "data.drop_outliers", False), ("shapenet_r2n2", "data.exclude_sequences", True),
    ("co3d", "data.train_view", 0), ("procedural", "data.train_view", 0),
])
def test_a_protocol_field_of_another_data_set_is_refused(kind, field, value):
    with pytest.raises(ConfigError, match=rf"{field}: only data.kind="):
        load_config(None, {"data.kind": kind, field: value})


def test_table_6_dry_runs_on_co3d_with_pc2s_protocol(tmp_path, monkeypatch, capsys):
    tree = make_co3d(tmp_path / "co3d", categories=("teddybear",), frames=3, splits={"train": 1, "val": 1, "test": 0})
    monkeypatch.setenv("CDM_INPUTS", str(paper_inputs(tmp_path / "inputs", _cfg(tree.root))))
    monkeypatch.chdir(tmp_path)
    spec = Path(__file__).resolve().parent.parent / "sweeps" / "prior_type.yaml"
    sets = {"data.kind": "co3d", "data.root": str(tree.root)}
    assert run.main([str(spec), "--dry-run", "--no-estimate", "--profile", "paper",
                     *[a for k, v in sets.items() for a in ("--set", f"{k}={v}")]]) == 0
    out = capsys.readouterr().out
    plan = expand(load_spec(spec), "paper", sets)
    assert sorted(c.paper_label for c in plan.cells) == ["contour, teddybear", "depth, teddybear"]
    for cell in plan.cells:
        d = cell.config.data
        assert cell.label in out
        assert (
            d.exclude_sequences,
            d.frames_per_sequence,
            d.mask_rgb,
            d.drop_outliers,
            cell.config.model.mask_channels,
        ) == (True, 1, True, False, True)
        assert (d.num_points, cell.config.priors.render_kind, cell.config.priors.depth_source) == (
            16384,
            "depth",
            "maps",
        )
    assert f"priors.depth_maps={tmp_path / 'inputs' / 'depth_maps'} (ok)" in out
