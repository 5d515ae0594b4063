"""``python -m cdm.tools.estimate_depth``: tiny randomly initialised DPT / Depth Anything models, built from
their configs here (no download), on views exported from the Co3D fixture."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cdm.data.depth_maps import DepthMaps
from cdm.external_inputs import check_coverage
from cdm.tools.estimate_depth import estimate, load_estimator
from cdm.tools.estimate_depth import main as estimate_main
from cdm.tools.export_views import main as export_main
from sweeps.inputs import main as inputs_main
from tests.conftest import tiny_config
from tests.datasets_fixtures import make_co3d

transformers = pytest.importorskip("transformers", reason="the depth tool's optional extra: pip install -e '.[depth]'")


def _backbone():
    return transformers.Dinov2Config(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        image_size=56,
        patch_size=14,
        out_features=["stage1", "stage2", "stage3", "stage4"],
        reshape_hidden_states=False,
    )


def _save(model, folder: Path) -> str:
    torch.manual_seed(0)
    model.save_pretrained(folder)
    transformers.DPTImageProcessor(size={"height": 56, "width": 56}, keep_aspect_ratio=False).save_pretrained(folder)
    return str(folder)


def tiny_dpt(folder: Path) -> str:
    """DINOv2's DPT head, as ``facebook/dpt-dinov2-*`` build it, at toy size (it outputs depth), saved into
    ``folder``."""
    torch.manual_seed(0)
    config = transformers.DPTConfig(backbone_config=_backbone(), hidden_size=32, neck_hidden_sizes=[16, 16, 16, 16],
                                    fusion_hidden_size=16, head_hidden_size=16, reassemble_factors=[4, 2, 1, 0.5])
    return _save(transformers.DPTForDepthEstimation(config), folder)


@pytest.fixture(scope="module")
def dpt(tmp_path_factory) -> str:
    return tiny_dpt(tmp_path_factory.mktemp("dpt"))


@pytest.fixture(scope="module")
def depth_anything(tmp_path_factory) -> str:
    """Depth Anything's relative model at toy size: it outputs disparity."""
    torch.manual_seed(0)
    config = transformers.DepthAnythingConfig(
        backbone_config=_backbone(),
        reassemble_hidden_size=32,
        neck_hidden_sizes=[16, 16, 16, 16],
        fusion_hidden_size=16,
        head_hidden_size=16,
        reassemble_factors=[4, 2, 1, 0.5],
    )
    return _save(transformers.DepthAnythingForDepthEstimation(config), tmp_path_factory.mktemp("depth_anything"))


@pytest.fixture(scope="module")
def co3d(tmp_path_factory):
    """The Co3D fixture and its exported input crops (32²)."""
    tree = make_co3d(tmp_path_factory.mktemp("co3d"), categories=("teddybear",), frames=3)
    views = tmp_path_factory.mktemp("views")
    sets = ["data.kind=co3d", f"data.root={tree.root}", "data.image_size=32", "data.num_points=128"]
    assert export_main(["--out", str(views), *[a for s in sets for a in ("--set", s)]]) == 0
    return tree, views, dict(s.split("=", 1) for s in sets)


def _crops(views: Path) -> list[tuple[str, Path]]:
    """(object id, crop) of every input crop (ids are the folders under ``views``, e.g. ``co3d/teddybear/<seq>``)."""
    return sorted((str(p.parent.relative_to(views)), p) for p in views.rglob("*.png") if p.stem.isdigit())


def test_maps_match_each_crop_row_for_row_and_train_a_smoke_cell(co3d, dpt, tmp_path, capsys):
    tree, views, sets = co3d
    out = tmp_path / "maps"
    assert estimate_main(["--views", str(views), "--model", dpt, "--out", str(out), "--batch-size", "3"]) == 0
    crops = _crops(views)
    assert f"wrote {len(crops)} maps (0 already there)" in capsys.readouterr().out
    assert json.loads((out / "estimator.json").read_text()) == {"model": dpt, "disparity": False}
    estimator = load_estimator(dpt)
    for object_id, crop in crops:
        depth = np.load(out / object_id / f"{crop.stem}.npy")
        assert depth.shape == (32, 32) and depth.dtype == np.float32
        # Against the model's raw output resized by OpenCV (an independent bicubic): rows stay rows.
        rgb = cv2.cvtColor(cv2.imread(str(crop)), cv2.COLOR_BGR2RGB)
        with torch.inference_mode():
            raw = estimator.model(**estimator.processor(images=[rgb], return_tensors="pt")).predicted_depth[0].numpy()
        reference = cv2.resize(raw, (32, 32), interpolation=cv2.INTER_CUBIC)
        assert np.corrcoef(depth.ravel(), reference.ravel())[0, 1] > 0.98

    cfg = tiny_config(
        tmp_path,
        **{k: v for k, v in sets.items() if k != "data.num_points"},
        **{
            "data.categories": [],
            "priors.prior_2d": "depth",
            "priors.depth_source": "maps",
            "priors.depth_maps": str(out),
            "diffusion.clip_x0": None,
            "train.steps": 2,
            "train.eval_every": 2,
            "eval.save_clouds": 0,
        },
    )
    from cdm.data import build_dataset
    from cdm.train import fit

    check_coverage(cfg, [build_dataset(cfg, split) for split in ("train", "val")])
    result = fit(cfg)
    assert result.step == 2 and np.isfinite(result.metrics["eval/cd"])


def test_a_map_keeps_a_non_square_crops_rows_and_columns(dpt, tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (24, 40, 3), dtype=np.uint8)
    (maps,) = estimate(load_estimator(dpt), [rgb])
    assert maps.shape == (24, 40)


def test_disparity_models_set_the_flag_and_a_reader_with_the_wrong_flag_is_refused(
    co3d, depth_anything, tmp_path, capsys
):
    _, views, _ = co3d
    out = tmp_path / "maps"
    assert estimate_main(["--views", str(views), "--model", depth_anything, "--out", str(out)]) == 0
    assert "--set priors.depth_maps_disparity=true" in capsys.readouterr().out
    assert DepthMaps(out, disparity=True).folder == out
    with pytest.raises(
        ValueError, match="priors.depth_maps_disparity: .* holds disparity maps .*set priors.depth_maps_disparity=true"
    ):
        DepthMaps(out, disparity=False)


def test_a_rerun_keeps_the_maps_already_written(co3d, dpt, tmp_path, capsys):
    _, views, _ = co3d
    out = tmp_path / "maps"
    assert estimate_main(["--views", str(views), "--model", dpt, "--out", str(out)]) == 0
    object_id, first = _crops(views)[0]
    kept = out / object_id / f"{first.stem}.npy"
    kept.write_bytes(kept.read_bytes())  # mark it: a rerun that rewrote it would change its mtime
    stamp = kept.stat().st_mtime_ns
    (out / object_id / "1.npy").unlink()
    left = sum(1 for _ in out.rglob("*.npy"))
    capsys.readouterr()
    assert estimate_main(["--views", str(views), "--model", dpt, "--out", str(out)]) == 0
    assert kept.stat().st_mtime_ns == stamp
    assert f"wrote 1 maps ({left} already there)" in capsys.readouterr().out


def test_bad_arguments_give_one_line(co3d, dpt, depth_anything, tmp_path, capsys):
    _, views, _ = co3d
    cases = [
        (["--views", str(tmp_path), "--model", dpt], "--views: .* has no objects.json"),
        (["--views", str(views), "--model", str(tmp_path / "none")], "--model: .* is not a folder"),
        (["--views", str(views), "--model", dpt, "--batch-size", "0"], "--batch-size must be >= 1"),
    ]
    for args, message in cases:
        assert estimate_main([*args, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("error: ")
        assert re.search(message, err), err
    assert estimate_main(["--views", str(views), "--model", dpt, "--out", str(tmp_path / "mixed")]) == 0
    assert estimate_main(["--views", str(views), "--model", depth_anything, "--out", str(tmp_path / "mixed")]) == 2
    assert "holds maps of" in capsys.readouterr().err


def test_predicts_says_what_a_model_predicts_where_its_config_does_not(co3d, dpt, tmp_path, capsys):
    """GLPN's config does not say whether it predicts depth or disparity: the tool refuses to guess until
    ``--predicts`` says; ``--predicts`` also overrides the guess made for a known model (DINOv2's DPT: depth)."""
    _, views, _ = co3d
    torch.manual_seed(0)
    glpn = transformers.GLPNConfig(num_encoder_blocks=4, depths=[1, 1, 1, 1], sr_ratios=[8, 4, 2, 1],
                                   hidden_sizes=[8, 16, 32, 64], num_attention_heads=[1, 1, 2, 2],
                                   mlp_ratios=[2, 2, 2, 2], decoder_hidden_size=16)
    unknown = _save(transformers.GLPNForDepthEstimation(glpn), tmp_path / "glpn")
    capsys.readouterr()  # saving's progress bar
    assert estimate_main(["--views", str(views), "--model", unknown, "--out", str(tmp_path / "refused")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: --predicts: ") and "'glpn' model" in err
    assert "say which: --predicts depth or --predicts disparity" in err and not (tmp_path / "refused").exists()
    # The cluster's command (python sweeps/inputs.py depth) loads the model the same way, before Ray starts.
    assert inputs_main(["depth", "--views", str(views), "--model", unknown, "--out", str(tmp_path / "refused")]) == 2
    assert capsys.readouterr().err == err and not (tmp_path / "refused").exists()
    assert load_estimator(unknown, predicts="disparity").disparity
    out = tmp_path / "as_disparity"
    assert estimate_main(["--views", str(views), "--model", dpt, "--out", str(out), "--predicts", "disparity"]) == 0
    assert json.loads((out / "estimator.json").read_text()) == {"model": dpt, "disparity": True}
    assert "--set priors.depth_maps_disparity=true" in capsys.readouterr().out
