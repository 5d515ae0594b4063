"""Checkpoints that read as data but are wrong as checkpoints (issue 49, section 4): a cfg holding inf or
NaN, a model dict with an int key, a list or a NaN where a weight belongs, a path that is no file, and a
sweep whose dry run reads one. Each ends, through the command a user types, as exit 2 and one ``error:``
line naming the file and the field, no traceback."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest
import torch

from cdm.checkpoint import CHECKPOINT_FILE, Checkpoint, load_checkpoint, load_network, save_checkpoint
from cdm.config import load_config
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.model import CDMNetwork
from cdm.model.state_dicts import checked_state_dict
from tests.hostile_files import ROOT, assert_refused, run_command
from tests.pc2_files import PC2_CFG, write_pc2_checkpoint
from tests.test_pc2_checkpoint import SMALL

SETS = [arg for pair in SMALL for arg in ("--set", pair)]
FIRST = "point_cloud_model.model.sa_layers.0.0.point_features.layers.0.weight"


@pytest.fixture(scope="module")
def pc2_model(tmp_path_factory) -> dict[str, torch.Tensor]:
    """PC²'s model state dict at quarter width (written once; each case saves a changed copy)."""
    return write_pc2_checkpoint(tmp_path_factory.mktemp("pc2") / "checkpoint-latest.pth", width=0.25)


@pytest.mark.slow
@pytest.mark.parametrize("group, key, value", [
    ("dataset", "image_size", float("inf")),
    ("dataset", "image_size", float("nan")),
    ("model", "beta_start", float("nan")),
    ("dataset", "image_size", 100_000),  # a number, but no image size this code takes
])
def test_a_cfg_value_that_is_no_finite_number_is_named_with_its_file(tmp_path, group, key, value):
    path = tmp_path / "checkpoint-latest.pth"
    write_pc2_checkpoint(path, width=0.25, cfg={**PC2_CFG, group: {**PC2_CFG[group], key: value}})
    for command, flag in (("evaluate", "--checkpoint"), ("train", "--init-from")):
        line = assert_refused(run_command(["-m", "cdm", command, flag, str(path), *SETS], tmp_path),
                              f"error: {flag}: {path}: its cfg")
        assert f"{group}.{key}" in line or "data.image_size" in line, line
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_a_model_dict_holding_no_state_dict_or_non_finite_weights_is_refused_naming_the_weight(pc2_model, tmp_path):
    nan, inf = pc2_model[FIRST].clone(), pc2_model["feature_model.model.blocks.0.attn.qkv.weight"].clone()
    nan.view(-1)[5], inf.view(-1)[0] = float("nan"), float("-inf")
    cases = {
        "int_key.pth": ({**pc2_model, 5: torch.zeros(1)}, "holds a weight under the key 5 (int)"),
        "list.pth": ({**pc2_model, FIRST: [1.0, 2.0]}, f"holds weight '{FIRST}' as a Python list, not a tensor"),
        "nan.pth": ({**pc2_model, FIRST: nan}, f"holds NaN in weight '{FIRST}'"),
        "inf.pth": ({**pc2_model, "feature_model.model.blocks.0.attn.qkv.weight": inf},
                    "holds inf in weight 'feature_model.model.blocks.0.attn.qkv.weight'"),
    }
    for name, (model, needle) in cases.items():
        torch.save({"model": model, "step": 1}, tmp_path / name)
        assert_refused(run_command(["-m", "cdm", "evaluate", "--checkpoint", name, *SETS], tmp_path),
                       f"error: --checkpoint: {name} {needle}")
    assert_refused(run_command(["-m", "cdm", "train", "--init-from", "nan.pth", *SETS], tmp_path),
                   f"error: --init-from: nan.pth holds NaN in weight '{FIRST}'")
    # A sweep cell names the file as model.init_from: the network's own reader refuses it the same way.
    network = {"model.denoiser": "pvcnn2", "model.encoder": "vit_s16", "model.feature_dim": 384,
               "priors.prior_2d": "none", "model.width_multiplier": 0.25,
               "model.voxel_resolution_multiplier": 0.25, "data.image_size": 32}
    for name, needle in (("int_key.pth", "key 5 (int)"), ("nan.pth", f"NaN in weight '{FIRST}'")):
        pattern = f"^model.init_from: {re.escape(str(tmp_path / name))} .*{re.escape(needle)}"
        with pytest.raises(ValueError, match=pattern):
            load_network(None, {**network, "model.init_from": str(tmp_path / name)})


def _cdm_checkpoint(folder: Path, change) -> Path:
    cfg = load_config(None, {"data.image_size": 32, "data.num_points": 128, "eval.num_points": 128})
    model = dict(CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d]).state_dict())
    return save_checkpoint(Checkpoint(cfg.to_dict(), 0, "dense", change(model)), folder)


@pytest.mark.slow
def test_a_cdm_checkpoint_with_bad_weights_is_refused_in_one_line(tmp_path):
    def nan_first(model):
        first = next(iter(model))
        model[first] = model[first].clone().fill_(float("nan"))
        return model

    _cdm_checkpoint(tmp_path / "nan", nan_first)
    first = next(iter(CDMNetwork(load_config(None, {}).model, 1).state_dict()))
    assert_refused(run_command(["-m", "cdm", "evaluate", "--checkpoint", "nan", *SETS], tmp_path),
                   f"error: checkpoint: nan/model.safetensors holds NaN in weight '{first}'")
    with pytest.raises(ValueError, match=r"^train.out_dir: a tensor's name is 7 \(int\); safetensors names are "
                                         "strings$"):
        _cdm_checkpoint(tmp_path / "int_key", lambda m: {**m, 7: torch.zeros(1)})


def _damaged(raw: bytes) -> dict[str, bytes]:
    """A model.safetensors damaged each way a header can be, by the clause its refusal names."""
    length = int.from_bytes(raw[:8], "little")
    header, data = raw[8:8 + length], raw[8 + length:]
    first = next(end for begin, end in (e["data_offsets"] for e in json.loads(header).values()
                                         if "data_offsets" in e) if begin == 0)

    def edited(old: bytes, new: bytes) -> bytes:  # the header's length prefix kept true
        changed = header.replace(old, new, 1)
        return len(changed).to_bytes(8, "little") + changed + data

    return {
        "its tensors end at byte": raw[:-100],  # truncated in the weights
        "shorter than its header's length": raw[:5],
        "its header says 18446744073709551615 bytes": b"\xff" * 8 + raw[8:],  # oversized
        "is not JSON": edited(b'"', b"{"),  # malformed
        "has dtype 'F99'": edited(b'"F32"', b'"F99"'),
        "spans": edited(b'"shape":[', b'"shape":[2,'),
        "the tensors overlap or leave a gap": edited(b'"data_offsets":[0,%d]' % first,
                                                     b'"data_offsets":[4,%d]' % (first + 4)),
    }


def test_a_truncated_oversized_or_malformed_safetensors_header_is_a_value_error_naming_the_file(tmp_path):
    good = _cdm_checkpoint(tmp_path / "good", lambda m: m).parent
    raw = (good / "model.safetensors").read_bytes()
    for clause, damaged in _damaged(raw).items():
        folder = tmp_path / re.sub(r"[^a-z]+", "_", clause)
        shutil.copytree(good, folder)
        (folder / "model.safetensors").write_bytes(damaged)
        with pytest.raises(ValueError, match=rf"^checkpoint: {re.escape(str(folder / 'model.safetensors'))}.*"
                                             rf"{re.escape(clause)}"):
            load_checkpoint(folder)
    (good / CHECKPOINT_FILE).write_text(json.dumps({**json.loads((good / CHECKPOINT_FILE).read_text()),
                                                    "ema": "../../elsewhere.safetensors"}))
    with pytest.raises(ValueError, match=rf"^checkpoint: .*good/{CHECKPOINT_FILE}: its 'ema' is "
                                         r"'\.\./\.\./elsewhere\.safetensors'; expected ema\.safetensors$"):
        load_checkpoint(good)


def test_a_cdm_checkpoint_whose_weights_its_config_cannot_build_names_the_file_and_a_weight(tmp_path):
    folder = tmp_path / "run"
    _cdm_checkpoint(folder, lambda m: {k: v for k, v in m.items() if not k.startswith("denoiser.")})
    with pytest.raises(ValueError, match=rf"^checkpoint: {folder} holds weights its config's network cannot take: "
                                         r"Missing key\(s\) in state_dict: \"denoiser\."):
        load_network(folder, {"train.device": "cpu"})


def test_checked_state_dict_keeps_a_good_one_and_names_the_first_bad_entry():
    good = {"a": torch.ones(2), "n": torch.tensor([3])}
    assert checked_state_dict(good, "x") == good
    bad = {"a": torch.ones(2), "b": torch.tensor([1.0, float("nan")]), "c": torch.tensor([float("inf")])}
    with pytest.raises(ValueError, match=r"^x holds NaN in weight 'b'; a network computes nothing with it$"):
        checked_state_dict(bad, "x")
    with pytest.raises(ValueError, match=r"^x holds weight 'a' as a Python int, not a tensor$"):
        checked_state_dict({"a": 1}, "x")


@pytest.mark.slow
def test_train_init_from_names_what_the_path_is_instead_of_calling_it_missing(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "folder").mkdir()
    for path, kind in ((tmp_path / "folder", "a folder"), (Path("/dev/zero"), "a character device"),
                       (fifo, "a FIFO"), (tmp_path / "missing.pth", "does not exist")):
        line = assert_refused(run_command(["-m", "cdm", "train", "--init-from", str(path)], tmp_path, timeout=60),
                              f"error: --init-from: {path} ", kind, "pass PC²'s checkpoint-latest.pth")
        assert ("does not exist" in line) == (kind == "does not exist"), line


@pytest.mark.slow
def test_a_dry_run_plans_init_from_per_category_on_co3d_and_refuses_an_unreadable_one_in_one_line(tmp_path):
    """Every co3d cell has one category, so ``{category}`` is filled per cell (not "got []"); the files are
    there, so the calibration reads them and refuses one that is no torch file, in one line."""
    for category in ("bottle", "mug", "sofa"):
        (tmp_path / "pc2" / category).mkdir(parents=True)
        (tmp_path / "pc2" / category / "checkpoint-latest.pth").write_text("not a checkpoint\n")
    sets = ["--set", f"model.init_from={tmp_path}/pc2/{{category}}/checkpoint-latest.pth", "--set",
            "model.denoiser=pvcnn2", "--set", "model.encoder=vit_s16", "--set", "model.feature_dim=384"]
    spec = str(ROOT / "sweeps" / "co3d.yaml")
    planned = run_command([str(ROOT / "sweeps" / "run.py"), spec, "--dry-run",
                           "--no-estimate", *sets], tmp_path)
    assert planned.code == 0 and "got []" not in planned.stderr, planned.stderr[-2000:]
    assert f"model.init_from={tmp_path}/pc2/sofa/checkpoint-latest.pth (ok)" in planned.stdout
    refused = run_command([str(ROOT / "sweeps" / "run.py"), spec, "--dry-run", *sets], tmp_path)
    assert_refused(refused, "error: the cost estimate could not read an input: model.init_from: "
                            f"{tmp_path}/pc2/bottle/checkpoint-latest.pth is not a readable torch file")
    assert not (tmp_path / "results").exists() and not (tmp_path / "mlruns").exists()


def test_a_prior_whose_weights_its_config_cannot_build_and_a_pvd_file_with_nan_are_named(tmp_path):
    from cdm.config import ModelConfig
    from cdm.prior_model import PRIOR_KIND, PriorNetwork, load_prior

    cfg = load_config(None, {})
    model = {k: v for k, v in PriorNetwork(cfg.model).state_dict().items() if not k.endswith(".bias")}
    save_checkpoint(Checkpoint(cfg.to_dict(), 1, "dense", model, kind=PRIOR_KIND, category="chair"), tmp_path / "p")
    with pytest.raises(ValueError, match=rf"^sampling.blend.prior_checkpoint: {tmp_path / 'p'} holds weights its "
                                         r"config's network cannot take: Missing key\(s\)"):
        load_prior(tmp_path / "p")
    pvd = {f"model.module.{k}": v for k, v in
           PriorNetwork(ModelConfig(denoiser="pvcnn2", time_embed_dim=64)).denoiser.state_dict().items()}
    first = next(iter(pvd))
    pvd[first] = torch.full_like(pvd[first], float("inf"))
    torch.save({"model_state": pvd}, tmp_path / "prior.pth")
    with pytest.raises(ValueError, match=rf"not a PVD checkpoint we can read \(.*prior\.pth holds inf in weight "
                                         rf"'{re.escape(first)}'"):
        load_prior(tmp_path / "prior.pth")


@pytest.mark.parametrize("value", [-1.0, "7", None, 1e400])
def test_a_compute_count_that_is_no_finite_number_of_seconds_is_refused(tmp_path, value):
    file = _cdm_checkpoint(tmp_path / "ck", lambda m: m)
    record = json.loads(file.read_text())
    assert record["compute_s"] == 0.0
    file.write_text(json.dumps({**record, "compute_s": value}).replace("Infinity", "1e400"))
    with pytest.raises(ValueError, match=r"checkpoint\.json: its compute_s must be a finite number of seconds"):
        load_checkpoint(tmp_path / "ck")
