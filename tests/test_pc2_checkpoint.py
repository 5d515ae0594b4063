"""PC²'s checkpoint-latest.pth as its main.py saves it: recognised, cfg read as data, network rebuilt
key for key, scored and fine-tuned in one command; a cfg carrying a payload refused with nothing run."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cdm.__main__ import main
from cdm.checkpoint import load_checkpoint, load_network
from cdm.config import ConfigError, load_config, parse_override
from cdm.diffusion import SamplerSettings
from cdm.pc2_checkpoint import PC2_DEFAULTS, is_pc2_checkpoint, read_pc2_checkpoint
from tests.pc2_files import PC2_CFG, write_pc2_checkpoint

# Small enough to score in seconds: a quarter-width PVCNN2 (PC²'s key names, shapes at that width), 32² images.
SMALL = ["model.width_multiplier=0.25", "model.voxel_resolution_multiplier=0.25", "data.image_size=32",
         "data.num_points=128", "eval.num_points=128", "data.categories=[chair,mug]", "data.train_objects=2",
         "data.val_objects=1", "eval.num_objects=1", "eval.retrieval_bank=2", "diffusion.ddpm_steps=2",
         "train.threads=1", "eval.save_clouds=0"]


def _sets(extra: list[str] = ()) -> list[str]:
    return [arg for pair in [*SMALL, *extra] for arg in ("--set", pair)]


@pytest.fixture(scope="module")
def pc2_file(tmp_path_factory) -> tuple[Path, dict[str, torch.Tensor]]:
    path = tmp_path_factory.mktemp("pc2") / "checkpoint-latest.pth"
    return path, write_pc2_checkpoint(path, width=0.25)


def test_the_cfg_is_read_as_data_and_gives_pc2s_settings(pc2_file, tmp_path):
    path, _ = pc2_file
    assert is_pc2_checkpoint(path) and not is_pc2_checkpoint(tmp_path / "missing.pth")
    pc2 = read_pc2_checkpoint(path)
    o = pc2.overrides
    assert (o["model.denoiser"], o["model.encoder"], o["model.init_from"], o["model.feature_dim"]) == (
        "pvcnn2",
        "vit_s16",
        str(path),
        384,
    )
    assert (o["data.image_size"], o["data.num_points"], o["eval.num_points"]) == (
        224,
        16_384,
        16_384,
    )  # ${dataset.image_size} resolved
    assert (o["diffusion.sampler"], o["diffusion.ddpm_steps"], o["diffusion.clip_x0"], o["diffusion.beta_end"]) == (
        "ddpm",
        None,
        None,
        8e-3,
    )
    assert (o["model.time_embed_dim"], o["model.mask_channels"], o["priors.prior_2d"]) == (64, True, "none")
    assert pc2.step == 100_000 and pc2.trained_on == "co3dv2 hydrant" and pc2.source == "the file's cfg"
    assert "omegaconf" not in sys.modules  # no class the cfg names was imported
    co3d = pc2.config({"data.kind": "co3d", "data.root": "/data/co3d", "data.categories": ["hydrant"]})
    assert (
        co3d.data.mask_rgb,
        co3d.data.exclude_sequences,
        co3d.data.frames_per_sequence,
        co3d.data.drop_outliers,
    ) == (True, True, 1, False)
    assert "Co3D loaded as PC² (data.mask_rgb=True" in pc2.describe(co3d, {})[1]
    assert pc2.config({}).data.mask_rgb is False  # the embedded data set has no such option
    other = tmp_path / "other.pth"
    cfg = {**PC2_CFG, "dataset": {**PC2_CFG["dataset"], "image_size": 128, "max_points": 4096},
           "run": {**PC2_CFG["run"], "num_inference_steps": 100}}
    write_pc2_checkpoint(other, width=0.25, cfg=cfg)
    o = read_pc2_checkpoint(other).overrides
    assert (o["data.image_size"], o["data.num_points"], o["diffusion.ddpm_steps"]) == (128, 4096, 100)


def test_a_model_only_file_takes_pc2s_defaults_and_a_foreign_cfg_is_refused(pc2_file, tmp_path):
    path, model = pc2_file
    plain = tmp_path / "model_only.pth"
    torch.save({"model": model}, plain)
    pc2 = read_pc2_checkpoint(plain)
    assert (
        pc2.source.startswith("PC²'s defaults")
        and pc2.overrides["data.image_size"] == PC2_DEFAULTS["dataset.image_size"]
    )
    colour = tmp_path / "colour.pth"
    write_pc2_checkpoint(
        colour, width=0.25, cfg={**PC2_CFG, "model": {**PC2_CFG["model"], "use_global_features": True}}
    )
    with pytest.raises(ValueError, match=r"^--checkpoint: .*colour\.pth: its cfg asks for what this network cannot be: "
                                         r"model\.use_global_features=True"):
        read_pc2_checkpoint(colour)
    odd = tmp_path / "odd.pth"
    write_pc2_checkpoint(odd, width=0.25, cfg={**PC2_CFG, "dataset": {**PC2_CFG["dataset"], "max_points": "many"}})
    with pytest.raises(
        ValueError, match=r"^--checkpoint: .*odd\.pth: its cfg's dataset\.max_points is 'many', not an integer$"
    ):
        read_pc2_checkpoint(odd)
    write_pc2_checkpoint(odd, width=0.25, payload=["not", "a", "config"])
    with pytest.raises(ValueError, match=r"odd\.pth: its cfg is a list, not a config of groups"):
        read_pc2_checkpoint(odd)


def test_the_network_holds_the_files_weights_key_for_key(pc2_file):
    path, model = pc2_file
    small = {"model.width_multiplier": 0.25, "model.voxel_resolution_multiplier": 0.25, "data.image_size": 32}
    cfg, network, diffusion, _ = load_network(None, {**read_pc2_checkpoint(path).overrides, **small})
    for name, weight in network.denoiser.state_dict().items():
        assert torch.equal(weight, model[f"point_cloud_model.model.{name}"]), name
    for name, weight in network.encoder.backbone.state_dict().items():
        assert torch.equal(weight, model[f"feature_model.model.{name}"]), name
    assert diffusion.timesteps(SamplerSettings.from_config(cfg.diffusion)) == list(
        range(999, -1, -1)
    )  # PC²'s 1,000 DDPM steps


def test_a_cfg_with_a_payload_exits_2_with_one_line_and_runs_nothing(tmp_path, capsys):
    marker = tmp_path / "marker"

    class Payload:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    path = tmp_path / "checkpoint-latest.pth"
    write_pc2_checkpoint(path, width=0.25, payload={"run": Payload()})
    assert main(["evaluate", "--checkpoint", str(path), *_sets()]) == 2
    assert main(["train", "--init-from", str(path), *_sets()]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2
    for line, flag in zip(lines, ("--checkpoint", "--init-from")):
        assert line.startswith(
            f"error: {flag}: {path} could run code from the file while loading (it calls posix.system); refused, "
            "and nothing of it was run"
        )
    assert not marker.exists() and not (tmp_path / "runs").exists()
    network = {
        "model.denoiser": "pvcnn2",
        "model.encoder": "vit_s16",
        "model.feature_dim": 384,
        "priors.prior_2d": "none",
        "model.init_from": str(path),
    }  # as a sweep cell names it: the network reads the file itself
    with pytest.raises(ValueError, match=rf"^model.init_from: {path} could run code from the file while loading"):
        load_network(None, network)
    assert not marker.exists()
    assert main(["train", "--init-from", str(tmp_path / "missing.pth")]) == 2
    assert (
        capsys.readouterr().err
        == f"error: --init-from: {tmp_path / 'missing.pth'} does not exist; pass PC²'s checkpoint-latest.pth\n"
    )


def test_init_from_needs_pc2s_network_one_category_for_its_pattern_and_weights_that_fit(pc2_file, tmp_path):
    path, _ = pc2_file
    with pytest.raises(
        ConfigError, match="model.init_from: PC²'s weights need model.denoiser=pvcnn2 and model.encoder=vit_s16"
    ):
        load_config(None, {"model.init_from": str(path)})
    with pytest.raises(
        ConfigError, match=r"model.init_from: \{category\} in .* needs exactly one data.categories entry"
    ):
        load_config(
            None,
            {
                **read_pc2_checkpoint(path).overrides,
                "model.init_from": "/w/{category}.pth",
                "data.categories": ["a", "b"],
            },
        )
    one = load_config(
        None,
        {**read_pc2_checkpoint(path).overrides, "model.init_from": "/w/{category}.pth", "data.categories": ["mug"]},
    )
    assert one.model.init_from == "/w/mug.pth"
    with pytest.raises(ConfigError, match="eval.only scores the weights a run starts from"):
        load_config(None, {"eval.only": True})
    wide = read_pc2_checkpoint(path).overrides  # width 1: the file holds quarter-width weights
    with pytest.raises(
        ValueError, match=r"^model.init_from: .*checkpoint-latest\.pth: reference weight 'sa_layers.0.0"
    ):
        load_network(None, {**wide, "data.image_size": 32})


@pytest.mark.slow
def test_python_m_cdm_evaluate_and_reconstruct_take_pc2s_checkpoint_and_refuse_a_payload(pc2_file, tmp_path):
    path, _ = pc2_file
    out = subprocess.run([sys.executable, "-m", "cdm", "evaluate", "--checkpoint", str(path), *_sets()], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith(
        f"PC² checkpoint {path} (step 100000), trained on co3dv2 hydrant: PVCNN2 and its frozen ViT-S/16"
    )
    assert lines[1] == (
        "reference settings (the file's cfg): PC²'s DDPM sampler over 1000 steps, linear β 1e-05 → 0.008, "
        "ε-prediction, x̂₀ unclipped, 224² images, 16384 points, mask channels on"
    )
    assert "diffusion.ddpm_steps=2 (PC²: null)" in lines[2] and "data.image_size=32 (PC²: 224)" in lines[2]
    scores = {line.split()[0]: float(line.split()[1]) for line in lines[3:]}
    names = ["eval/cd", "eval/f1"] + [
        f"baseline/{b}/{m}" for b in ("sphere", "gaussian", "category_mean", "retrieval") for m in ("cd", "f1")
    ]
    assert set(names) <= set(scores) and all(scores[n] == scores[n] for n in names)  # every one a number, none NaN
    assert 0 <= scores["eval/f1"] <= 1 and scores["baseline/sphere/cd"] > 0
    image = tmp_path / "input.png"
    cv2.imwrite(
        str(image), np.full((32, 32, 3), 255, np.uint8) * (np.indices((32, 32)).sum(0) < 40)[..., None].astype(np.uint8)
    )
    out = subprocess.run([sys.executable, "-m", "cdm", "reconstruct", "--checkpoint", str(path), "--image", str(image),
                          "--ply", "cloud.ply", *_sets()], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"PC² checkpoint {path}") and "wrote 128 points to cloud.ply" in out.stdout
    marker = tmp_path / "marker"

    class Payload:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    evil = tmp_path / "evil.pth"
    write_pc2_checkpoint(evil, width=0.25, payload=Payload())
    out = subprocess.run([sys.executable, "-m", "cdm", "evaluate", "--checkpoint", str(evil), *_sets()], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and out.stdout == "" and not marker.exists()
    assert out.stderr.count("\n") == 1 and out.stderr.startswith(
        f"error: --checkpoint: {evil} could run code from the file"
    )


@pytest.mark.slow
def test_train_init_from_fine_tunes_from_the_weights_not_the_optimizer(pc2_file, tmp_path, capsys, monkeypatch):
    path, model = pc2_file
    monkeypatch.chdir(tmp_path)
    extra = ["train.steps=2", "train.eval_every=2", "train.batch_size=2", "priors.render_size=32", "priors.num_views=1",
             f"train.out_dir={tmp_path / 'run'}"]
    assert main(["train", "--init-from", str(path), *_sets(extra)]) == 0
    out = capsys.readouterr().out
    assert "the file's optimizer, scheduler and step are not loaded (a fresh AdamW, warm-up and step 0)" in out
    assert "done at step 2" in out
    ckpt = dataclasses.asdict(load_checkpoint(tmp_path / "run" / "checkpoints" / "step_0000002"))
    assert ckpt["step"] == 2 and ckpt["config"]["model"]["init_from"] == str(path)
    moved = [k for k, v in ckpt["model"].items() if k.startswith("denoiser.")
             and not torch.equal(v, model[f"point_cloud_model.model.{k.removeprefix('denoiser.')}"])]
    assert moved  # two AdamW steps moved the weights it started from …
    stem = ckpt["model"]["denoiser.sa_layers.0.0.point_features.layers.0.weight"]
    start = model["point_cloud_model.model.sa_layers.0.0.point_features.layers.0.weight"]
    assert (stem - start).abs().max() < 1e-2  # … by a warm-up's few steps, from PC²'s weights, not a fresh init


RELEASED = ("  - {label: PC² (released weights), set: {priors.prior_2d: none, priors.prior_3d: false, eval.only: true, "
            "model.init_from: '$CDM_INPUTS/pc2/{category}/checkpoint-latest.pth', model.encoder_weights: null}}\n")


def test_a_sweep_cell_names_pc2s_released_weights_and_a_missing_file_stops_it_before_ray(tmp_path, monkeypatch, capsys):
    """Table 3's spec with docs/paper.md's extra cell: PC²'s released weights, one file per category."""
    from sweeps import run
    from tests.input_fixtures import paper_inputs

    text = (Path(run.__file__).parent / "co3d.yaml").read_text()
    spec = tmp_path / "co3d_released.yaml"
    spec.write_text(text.replace("cells:\n", "cells:\n" + RELEASED, 1).replace("name: co3d", "name: co3d_released", 1))
    inputs = paper_inputs(tmp_path / "inputs")
    monkeypatch.setenv("CDM_INPUTS", str(inputs))
    monkeypatch.chdir(tmp_path)
    assert run.main([str(spec), "--dry-run", "--no-estimate", "--profile", "paper"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        f"error: model.init_from: {inputs}/pc2/bottle/checkpoint-latest.pth does not exist (a file of PC²'s checkpoint"
    )
    assert not (tmp_path / "ray_results").exists() and not (tmp_path / "mlruns").exists()
    for category in ("bottle", "mug", "sofa"):  # the procedural stand-ins of hydrant, teddybear, toytruck
        (inputs / "pc2" / category).mkdir(parents=True)
        (inputs / "pc2" / category / "checkpoint-latest.pth").write_bytes(b"")  # a dry run reads none of it
    assert run.main([str(spec), "--dry-run", "--no-estimate", "--profile", "paper"]) == 0
    out = capsys.readouterr().out
    assert (
        "PC² (released weights) · categories=sofa · seed 0: inputs: "
        f"model.init_from={inputs}/pc2/sofa/checkpoint-latest.pth (ok)\n"
        in out
    )
    # … its ViT-S/16 from the same file, not MSN's (the retrained cells read that one)
    listed = " ".join(out.split())  # the plan folds its lines at 120 columns
    assert (
        "1. PC² (released weights) · categories=bottle · seed 0 (priors.prior_2d=none, priors.prior_3d=False, "
        "eval.only=True, model.init_from=$CDM_INPUTS/pc2/{category}/checkpoint-latest.pth, "
        "model.encoder_weights=None, data.categories=['bottle']) "
        "[paper Table 3 · PC², hydrant (bottle stands in): eval/cd 92.32, eval/f1 0.485]"
    ) in listed


def test_eval_only_scores_the_starting_weights_at_step_0(pc2_file, tmp_path):
    from cdm.train import fit

    path, _ = pc2_file
    small = dict(parse_override(s) for s in SMALL)
    cfg = load_config(None, {**read_pc2_checkpoint(path).overrides, **small, "eval.only": True,
                             "train.out_dir": str(tmp_path / "run"), "priors.render_size": 32})
    result = fit(cfg)
    assert result.step == 0 and result.checkpoint_dir.name == "step_0000000"
    assert {"eval/cd", "eval/f1", "baseline/retrieval/cd"} <= set(result.metrics)
