"""ShapeNet (R2N2 renderings + PC15k clouds) on a small tree in the published layout."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cdm.__main__ import main
from cdm.cameras import select_sequence_views
from cdm.config import load_config
from cdm.data import build_dataset, list_categories
from cdm.data.checks import inside_mask
from cdm.data.priors2d import depth_prior_from_map
from cdm.data.shapenet import R2N2_FOCAL, SYNSETS
from sweeps import run
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from tests.datasets_fixtures import (
    SHAPENET_SYNSETS,
    make_shapenet,
    mask_check_report,
    mirrored,
    mirrored_x,
    project,
    r2n2_pixels,
    ramp_depth,
    unmapped_frame,
    write_depth_maps,
    wrong_distance,
)
from tests.input_fixtures import paper_inputs


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return make_shapenet(tmp_path_factory.mktemp("shapenet"))


def _cfg(root, **overrides):
    return load_config(None, {"data.kind": "shapenet_r2n2", "data.root": str(root), "data.image_size": 64,
                              "data.num_points": 4096, **overrides})


def test_samples_have_the_published_shapes_and_our_scales(tree):
    ds = build_dataset(_cfg(tree.root), "val")
    for i in range(len(ds)):
        s = ds[i]
        assert s.image.shape == (3, 64, 64) and s.image.dtype == torch.float32
        assert 0.0 <= s.image.min() and s.image.max() <= 1.0
        assert s.mask.shape == (1, 64, 64) and set(s.mask.unique().tolist()) == {0.0, 1.0}
        assert 0.05 < s.mask.mean() < 0.7
        # Composited on white: away from the silhouette's edge the background is exactly 1.
        far = torch.from_numpy(cv2.dilate(s.mask[0].numpy(), np.ones((5, 5), np.uint8)) == 0)
        assert torch.all(s.image[:, far] == 1.0)
        assert s.depth is None and s.prior_2d.shape == (1, 64, 64)  # R2N2 has no depth; contour prior
        assert s.points.shape == (4096, 3)
        assert len(ds.record(i).cloud) == 15000  # every PC15k point, in BDM's frame (values: the test below)
        assert s.camera.focal.item() == pytest.approx(R2N2_FOCAL) and torch.all(s.camera.principal == 0)
        assert s.view_cameras.batch_shape == (10,)
        assert torch.equal(s.view_cameras.R[0], s.camera.R) and torch.equal(s.view_cameras.T[0], s.camera.T)


def test_ground_truth_projects_into_the_mask_and_a_mirror_does_not(tree):
    cfg = _cfg(tree.root, **{"data.image_size": 137})  # R2N2's own resolution
    mirror = []
    for split in ("train", "val"):
        ds = build_dataset(cfg, split)
        for i in range(len(ds)):
            for round_ in range(3):
                s = ds.sample(i, round_)
                assert inside_mask(s.points, s.camera, s.mask) >= 0.95, (s.object_id, round_)
                mirror.append(inside_mask(s.points, mirrored(s.camera), s.mask))
                # Every prior view frames the whole object.
                for k in range(len(s.view_cameras)):
                    assert project(s.points, s.view_cameras[k])[:, :2].abs().max() < 1.0
    assert np.mean(mirror) < 0.8  # the check tells a mirrored camera apart (some views look alike mirrored)


@pytest.mark.parametrize("split", ["train", "val"])
def test_mask_check_passes_on_every_view_and_its_negative_controls_fail(tree, split):
    ds = build_dataset(_cfg(tree.root, **{"data.image_size": 137}), split)
    checks = mask_check_report(ds)
    assert all(c.passed for c in checks) and all(len(c.fractions) == 24 for c in checks)
    assert min(float(c.fractions.min()) for c in checks) >= 0.95
    for control in (unmapped_frame, mirrored_x, wrong_distance):
        bad = mask_check_report(ds, control)
        assert not any(c.passed for c in bad), control.__name__
        assert np.mean([float(c.fractions.mean()) for c in bad]) < 0.8, control.__name__


def test_pc15k_clouds_are_stored_in_the_v2_frame_and_loaded_in_v1(tree):
    """The published frames: the .npy holds v2 points; the loader's cloud is their v1 image (−z, y, −x) in
    BDM's global normalisation, (x − μ)/σ with μ the mean point and σ the std (n − 1) of every coordinate
    of the category's rendered training clouds, so the renderings' own camera sees it on the mask."""
    ds = build_dataset(_cfg(tree.root), "val")
    rec = ds.record(0)
    category, model = ds.objects[0].category, ds.objects[0].object_id.split("/")[-1]
    synset = SHAPENET_SYNSETS[category]

    def v1_of(folder, name):
        raw = np.load(tree.root / "ShapeNetCore.v2.PC15k" / synset / folder / f"{name}.npy").astype(np.float64)
        return np.stack([-raw[:, 2], raw[:, 1], -raw[:, 0]], 1)

    training = np.stack([v1_of("train", m) for m in tree.splits[category]["train"]])  # (K, 15000, 3), no unrendered
    mean, std = training.reshape(-1, 3).mean(0), training.reshape(-1).std(ddof=1)
    v1 = v1_of("val", model)
    assert rec.scale == pytest.approx(1 / std, rel=1e-12)
    assert np.abs(rec.cloud.numpy() - (v1 - mean) / std).max() < 1e-5
    meta = np.loadtxt(tree.root / "ShapeNetRendering" / synset / model / "rendering" / "rendering_metadata.txt")
    u, v, _ = r2n2_pixels(v1, *meta[0, [0, 1]], meta[0, 3] * 1.75)
    alpha = cv2.imread(str(tree.root / "ShapeNetRendering" / synset / model / "rendering" / "00.png"),
                       cv2.IMREAD_UNCHANGED)[..., 3]
    inside = alpha[np.clip(v.astype(int), 0, 136), np.clip(u.astype(int), 0, 136)] > 127
    assert inside.mean() > 0.95


def test_check_data_command_passes_the_published_frames_and_fails_clouds_left_unmapped(tree, tmp_path, capsys):
    args = ["check-data", "--set", "data.kind=shapenet_r2n2", "--set", "data.image_size=64"]
    assert main([*args, "--set", f"data.root={tree.root}"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("8/8 objects pass")
    # The same tree with every PC15k cloud already in R2N2's v1 frame: the loader's map now turns it wrong.
    root = tmp_path / "v1"
    shutil.copytree(tree.root, root)
    for npy in (root / "ShapeNetCore.v2.PC15k").rglob("*.npy"):
        v2 = np.load(npy)
        np.save(npy, np.stack([-v2[:, 2], v2[:, 1], -v2[:, 0]], 1))
    assert main([*args, "--set", f"data.root={root}"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[-1].startswith("0/8 objects pass") and sum(line.startswith("FAIL ") for line in out) == 8


def test_ground_truth_in_mask_at_the_training_size(tree):
    ds = build_dataset(_cfg(tree.root), "train")
    fractions = [
        inside_mask(ds.sample(i, r).points, ds.sample(i, r).camera, ds.sample(i, r).mask)
        for i in range(len(ds))
        for r in range(2)
    ]
    assert min(fractions) >= 0.95 and np.mean(fractions) > 0.98


def test_prior_views_are_the_renderings_in_azimuth_order_from_the_input(tree):
    ds = build_dataset(_cfg(tree.root), "val")
    record = ds.record(0)
    s = ds[0]
    positions = select_sequence_views(24, int(record.views[0]), 10)
    assert torch.equal(s.view_cameras.R[1:], record.sequence.R[positions[1:]])
    # Sorted by azimuth: every step turns the camera the same way, by less than a half turn.
    centres = -(record.sequence.T[:, None, :] @ record.sequence.R.transpose(1, 2))[:, 0]  # camera centres
    azimuth = torch.atan2(centres[:, 0], centres[:, 2])
    turn = torch.remainder(azimuth.roll(-1) - azimuth + torch.pi, 2 * torch.pi) - torch.pi  # signed, in (−π, π]
    assert torch.all(turn < 0) or torch.all(turn > 0)
    assert turn.sum().abs() == pytest.approx(2 * torch.pi, abs=1e-3)  # one full turn


def test_split_filtering_follows_pc15k_folders_and_skips_unrendered_models(tree):
    def models(split, **overrides):
        return {ref.object_id.split("/")[-1] for ref in build_dataset(_cfg(tree.root, **overrides), split).objects}

    for published, ours, overrides in (
        ("train", "train", {}),
        ("val", "val", {}),
        ("test", "val", {"data.eval_split": "test"}),
    ):
        expected = {m for name in SHAPENET_SYNSETS for m in tree.splits[name][published]}
        assert models(ours, **overrides) == expected
    assert not set(tree.unrendered) & models("train")


def test_bdm_split_file_gives_r2n2_splits_and_names_a_missing_split(tmp_path, capsys):
    tree = make_shapenet(tmp_path / "bdm", per_split={"train": 2, "val": 1, "test": 1}, bdm_split=True)

    def models(split, **overrides):
        return {ref.object_id.split("/")[-1] for ref in build_dataset(_cfg(tree.root, **overrides), split).objects}

    r2n2_test = {m for name in SHAPENET_SYNSETS for m in tree.bdm_split["test"][name]}
    assert models("val", **{"data.eval_split": "test"}) == r2n2_test and len(r2n2_test) == 4
    assert models("train") == {m for name in SHAPENET_SYNSETS for m in tree.bdm_split["train"][name]}
    assert _prepare(tree.root, tmp_path / "out", "--set", "data.eval_split=val") == 2
    err = capsys.readouterr().err
    assert "error: data.eval_split:" in err and "data.eval_split=test" in err


def test_category_mapping_names_and_synsets(tree):
    assert list_categories(_cfg(tree.root)) == ("airplane", "chair")  # only synsets present in both folders
    assert list_categories(_cfg(tree.root, **{"data.categories": ["03001627"]})) == ("chair",)
    assert SYNSETS[SHAPENET_SYNSETS["airplane"]] == "airplane" and len(SYNSETS) == 13
    ds = build_dataset(_cfg(tree.root), "train")
    assert [ref.category for ref in ds.objects[:4]] == ["airplane", "chair", "airplane", "chair"]  # interleaved
    assert all(ref.object_id.startswith(f"shapenet/{ref.category}/") for ref in ds.objects)
    with pytest.raises(ValueError, match="data.categories.*sofa"):
        build_dataset(_cfg(tree.root, **{"data.categories": ["sofa"]}), "train")


def test_held_out_view_is_00_and_training_rounds_vary_the_view(tree):
    ds = build_dataset(_cfg(tree.root, **{"data.image_size": 137}), "val")
    synset, model = SHAPENET_SYNSETS[ds.objects[0].category], ds.objects[0].object_id.split("/")[-1]
    alpha = cv2.imread(
        str(tree.root / "ShapeNetRendering" / synset / model / "rendering" / "00.png"), cv2.IMREAD_UNCHANGED
    )[..., 3]
    assert torch.equal(ds[0].mask[0], torch.from_numpy(alpha > 127).float())
    train = build_dataset(_cfg(tree.root), "train")
    assert len({tuple(train.sample(0, r).camera.T.tolist()) for r in range(6)}) >= 3


def _prepare(root, out, *extra):
    return main(
        [
            "prepare",
            "--set",
            "data.kind=shapenet_r2n2",
            "--root",
            str(root),
            "--out",
            str(out),
            "--set",
            "data.image_size=32",
            *extra,
        ]
    )


def test_cli_errors_name_the_path(tree, tmp_path, capsys):
    assert _prepare(tmp_path / "nowhere", tmp_path / "out") == 2
    assert "nowhere" in capsys.readouterr().err
    partial = tmp_path / "partial"
    shutil.copytree(tree.root / "ShapeNetRendering", partial / "ShapeNetRendering")
    assert _prepare(partial, tmp_path / "out") == 2
    assert f"{partial / 'ShapeNetCore.v2.PC15k'} is missing" in capsys.readouterr().err
    assert _prepare(tree.root, tmp_path / "out", "--set", "data.categories=[sofa]") == 2
    err = capsys.readouterr().err
    assert err.startswith("error: data.categories: ['sofa'] not in") and "airplane, chair" in err
    assert (
        main(
            [
                "train",
                "--set",
                "data.kind=shapenet_r2n2",
                "--set",
                f"data.root={tree.root}",
                "--set",
                "priors.prior_2d=depth",
                "--set",
                f"train.out_dir={tmp_path / 'run'}",
            ]
        )
        == 2
    )
    assert "priors.prior_2d" in capsys.readouterr().err and not (tmp_path / "run").exists()
    assert not (tmp_path / "out").exists()  # nothing written before the input is known good


def test_corrupt_image_exits_2_naming_it_and_leaves_no_partial_shard(tree, tmp_path, capsys):
    root = tmp_path / "copy"
    shutil.copytree(tree.root, root)
    model = tree.splits["chair"]["train"][1]
    png = root / "ShapeNetRendering" / SHAPENET_SYNSETS["chair"] / model / "rendering" / "00.png"
    png.write_bytes(png.read_bytes()[:200])  # truncated mid-stream
    out = tmp_path / "out"
    assert _prepare(root, out, "--set", "data.categories=[chair]") == 2
    err = capsys.readouterr().err
    last = err.splitlines()[-1]  # after the progress bar, one error line
    assert last.startswith("error: data.root: cannot read image") and str(png) in last and err.count("error:") == 1
    shards = sorted(out.rglob("*.safetensors"))
    assert len(shards) == 1 and not list(out.rglob(".*tmp*"))  # the object before it is complete; nothing half-written


# --- BDM's protocol (data.train_view, model.mask_channels) and Table 6's depth prior from estimated maps ---


def test_train_view_shows_that_rendering_in_every_round(tree, tmp_path):
    for view in (0, 5):
        ds = build_dataset(_cfg(tree.root, **{"data.train_view": view}), "train")
        for i in range(len(ds)):
            want = ds.view(i, view)  # rendering <view>.png
            for r in range(4):
                s = ds.sample(i, r)
                assert torch.equal(s.camera.T, want.camera.T) and torch.equal(
                    s.mask[0], torch.from_numpy(want.mask > 127).float()
                )
    assert torch.equal(
        build_dataset(_cfg(tree.root, **{"data.train_view": 5}), "val")[0].mask,
        build_dataset(_cfg(tree.root), "val")[0].mask,
    )
    two = make_shapenet(tmp_path / "two", per_split={"train": 1, "test": 1}, views=2)
    with pytest.raises(ValueError, match=r"data.train_view: 2, but shapenet/\w+/\w+ has 2 input views"):
        build_dataset(_cfg(two.root, **{"data.train_view": 2}), "train").sample(0)


def test_depth_prior_reads_the_estimated_map_of_the_view_shown(tree, tmp_path):
    with pytest.raises(ValueError, match="priors.prior_2d: 'depth' on ShapeNet needs estimated maps"):
        build_dataset(_cfg(tree.root, **{"priors.prior_2d": "depth"}), "val")
    write_depth_maps(tmp_path / "maps", _cfg(tree.root))
    estimated = {"priors.prior_2d": "depth", "priors.depth_source": "maps", "priors.depth_maps": str(tmp_path / "maps")}
    for split, view in (("train", 3), ("val", 0)):
        ds = build_dataset(_cfg(tree.root, **estimated, **{"data.train_view": 3}), split)
        for i in range(len(ds)):
            s = ds.sample(i, 1)
            position = int(ds.record(i).views[view])
            depth = torch.from_numpy(cv2.resize(ramp_depth(position), (64, 64), interpolation=cv2.INTER_NEAREST))[None]
            assert s.depth is None and torch.equal(s.prior_2d, depth_prior_from_map(depth, s.mask))
            assert s.prior_2d.max() == 1.0 and torch.all(s.prior_2d[s.mask == 0] == 0)


def test_table_6_dry_runs_on_shapenet_with_estimated_depth_and_bdms_protocol(tmp_path, monkeypatch, capsys):
    tree = make_shapenet(tmp_path / "shapenet", per_split={"train": 2, "val": 0, "test": 1}, views=2, bdm_split=True)
    monkeypatch.setenv(
        "CDM_INPUTS", str(paper_inputs(tmp_path / "inputs", _cfg(tree.root, **{"data.eval_split": "test"})))
    )
    monkeypatch.chdir(tmp_path)
    spec = Path(__file__).resolve().parent.parent / "sweeps" / "prior_type.yaml"
    sets = {"data.kind": "shapenet_r2n2", "data.root": str(tree.root)}
    assert run.main([str(spec), "--dry-run", "--no-estimate", "--profile", "paper",
                     *[a for k, v in sets.items() for a in ("--set", f"{k}={v}")]]) == 0
    out = capsys.readouterr().out
    plan = expand(load_spec(spec), "paper", sets)
    assert sorted(c.paper_label for c in plan.cells) == [
        "contour, airplane",
        "contour, chair",
        "depth, airplane",
        "depth, chair",
    ]
    for cell in plan.cells:  # one model per class, BDM's view 00 and conditioning channels
        cfg = cell.config
        assert cell.label in out and len(cfg.data.categories) == 1
        assert (cfg.data.train_view, cfg.model.mask_channels, cfg.priors.render_kind, cfg.data.eval_split) == (
            0,
            False,
            "planar",
            "test",
        )
    depth = [c.config for c in plan.cells if c.config.priors.prior_2d == "depth"]
    assert {(cfg.priors.depth_source, cfg.priors.depth_maps) for cfg in depth} == {("maps", "$CDM_INPUTS/depth_maps")}
    assert f"priors.depth_maps={tmp_path / 'inputs' / 'depth_maps'} (ok)" in out
