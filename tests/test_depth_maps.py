"""Estimated depth maps as the depth 2D prior (``priors.depth_source: maps``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cdm.config import ConfigError, load_config
from cdm.data import build_dataset
from cdm.external_inputs import check_coverage, check_inputs
from tests.datasets_fixtures import make_co3d


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return make_co3d(tmp_path_factory.mktemp("co3d"), categories=("teddybear",))


def _cfg(root, **overrides):
    return load_config(
        None,
        {
            "data.kind": "co3d",
            "data.root": str(root),
            "data.image_size": 32,
            "data.num_points": 256,
            "priors.num_views": 2,
            "priors.prior_2d": "depth",
            **overrides,
        },
    )


def _write_maps(folder, cfg, transform):
    """Each input view's ground-truth depth, transformed, as ``<object_id>/<position>.npy``."""
    for split in ("train", "val"):
        ds = build_dataset(cfg, split)
        for index, ref in enumerate(ds.objects):
            record = ds.surface(index)
            (folder / ref.object_id).mkdir(parents=True, exist_ok=True)
            for v, position in enumerate(record.views.tolist()):
                view = ds.view(index, v)
                depth = view.depth.astype(np.float32) * view.depth_scale
                np.save(
                    folder / ref.object_id / f"{position}.npy",
                    np.where(depth > 0, transform(np.maximum(depth, 1e-6)), 0.0),
                )


@pytest.mark.parametrize(("transform", "disparity"), [(lambda d: 2.5 * d + 7.0, False), (lambda d: 3.0 / d, True)])
def test_maps_up_to_scale_and_shift_give_the_ground_truth_prior(tree, tmp_path, transform, disparity):
    gt_cfg = _cfg(tree.root)
    _write_maps(tmp_path / "maps", gt_cfg, transform)
    cfg = _cfg(tree.root, **{"priors.depth_source": "maps", "priors.depth_maps": str(tmp_path / "maps"),
                             "priors.depth_maps_disparity": disparity})
    check_inputs(cfg)
    for split in ("train", "val"):
        gt, est = build_dataset(gt_cfg, split), build_dataset(cfg, split)
        check_coverage(cfg, (est,))
        for i in range(len(gt)):
            for r in range(3 if split == "train" else 1):
                a, b = gt.sample(i, r), est.sample(i, r)
                assert torch.equal(a.image, b.image) and torch.equal(a.depth, b.depth)
                assert b.prior_2d.max() == pytest.approx(1.0) and torch.allclose(a.prior_2d, b.prior_2d, atol=1e-4)


def test_an_estimate_differs_from_the_ground_truth(tree, tmp_path):
    gt_cfg = _cfg(tree.root)
    _write_maps(tmp_path / "maps", gt_cfg, lambda d: d + 0.3 * np.sin(7 * d))
    cfg = _cfg(tree.root, **{"priors.depth_source": "maps", "priors.depth_maps": str(tmp_path / "maps")})
    a, b = build_dataset(gt_cfg, "val").sample(0), build_dataset(cfg, "val").sample(0)
    assert not torch.allclose(a.prior_2d, b.prior_2d, atol=1e-3)
    mask = a.mask > 0.5
    assert (b.prior_2d[~mask] == 0).all()  # the background stays 0, whatever the map says there


def test_bad_maps_name_the_field(tree, tmp_path):
    gt_cfg = _cfg(tree.root)
    _write_maps(tmp_path / "maps", gt_cfg, lambda d: d)
    cfg = _cfg(tree.root, **{"priors.depth_source": "maps", "priors.depth_maps": str(tmp_path / "maps")})
    ds = build_dataset(cfg, "val")
    obj = ds.objects[0].object_id
    position = int(ds.surface(0).views[0])
    np.save(tmp_path / "maps" / obj / f"{position}.npy", np.zeros((2, 32, 32), np.float32))
    with pytest.raises(ValueError, match=r"priors.depth_maps: .* must be a 2-D float array \(h, w\)"):
        ds.sample(0)
    (tmp_path / "maps" / obj / f"{position}.npy").unlink()
    with pytest.raises(ValueError, match=r"priors.depth_maps: .* does not exist \(object"):
        ds.sample(0)
    for f in (tmp_path / "maps" / obj).iterdir():
        f.unlink()
    (tmp_path / "maps" / obj).rmdir()
    with pytest.raises(ValueError, match=rf"priors.depth_maps: no maps for object id '{obj}'"):
        check_coverage(cfg, (ds,))
    with pytest.raises(ValueError, match="priors.depth_maps: .*elsewhere does not exist"):
        check_inputs(
            _cfg(tree.root, **{"priors.depth_source": "maps", "priors.depth_maps": str(tmp_path / "elsewhere")})
        )
    with pytest.raises(ConfigError, match="priors.depth_source=maps needs a captured data set"):
        load_config(None, {"priors.prior_2d": "depth", "priors.depth_source": "maps", "priors.depth_maps": "x"})
    with pytest.raises(ValueError, match="priors.depth_maps: not set and data.root .* holds no estimated depth maps"):
        build_dataset(_cfg(tree.root, **{"priors.depth_source": "maps"}), "val")


def test_protocol_card_names_encoder_and_depth_unless_weights_and_maps_are_given(tmp_path):
    from sweeps.plan.protocol import plan_card
    from sweeps.plan.spec import load_spec
    from sweeps.plan.trials import expand

    root = make_co3d(tmp_path / "co3d3", categories=("hydrant", "teddybear", "toytruck"), frames=3,
                     splits={"train": 1, "val": 1, "test": 0}).root
    spec = load_spec(Path(__file__).resolve().parent.parent / "sweeps" / "co3d.yaml")
    def listed(card):  # the fields the card lists
        return {line.split(":")[0] for line in card.deviations}

    paper = listed(plan_card(expand(spec, "paper", {"data.root": str(root)})))  # the profile's: ViT, estimated maps
    assert not {"model.encoder", "priors.depth_source"} & paper
    stand_ins = expand(
        spec, "paper", {"data.root": str(root), "model.encoder": "cnn", "priors.depth_source": "ground_truth"}
    )
    assert listed(plan_card(stand_ins)) - paper == {"model.encoder", "priors.depth_source"}


def test_prepare_stores_the_maps_in_the_shards(tree, tmp_path, capsys):
    from cdm.__main__ import main

    gt_cfg = _cfg(tree.root)
    _write_maps(tmp_path / "maps", gt_cfg, lambda d: 4.0 * d + 1.0)
    args = [
        "prepare",
        "--set",
        "data.kind=co3d",
        "--root",
        str(tree.root),
        "--set",
        "data.image_size=32",
        "--set",
        "data.categories=[teddybear]",
    ]
    assert main([*args, "--out", str(tmp_path / "prepared"), "--depth-maps", str(tmp_path / "maps")]) == 0
    sets = {"priors.depth_source": "maps"}
    from_shards = _cfg(tmp_path / "prepared", **sets)
    from_folder = _cfg(tree.root, **sets, **{"priors.depth_maps": str(tmp_path / "maps")})
    for split in ("train", "val"):
        a, b = build_dataset(from_folder, split), build_dataset(from_shards, split)
        for i in range(len(a)):
            assert torch.equal(a.sample(i, 1).prior_2d, b.sample(i, 1).prior_2d)
    first = build_dataset(gt_cfg, "train").objects[0].object_id
    for f in (tmp_path / "maps" / first).iterdir():
        f.unlink()
    (tmp_path / "maps" / first).rmdir()
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "other"), "--depth-maps", str(tmp_path / "maps")]) == 2
    assert f"error: priors.depth_maps: no maps for object id '{first}'" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()  # refused before anything is written
