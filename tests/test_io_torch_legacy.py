"""torch < 1.6's pre-zip files (cdm.io.torch.legacy, issue 55 §1): written by torch's own
``torch.save(..., _use_new_zipfile_serialization=False)`` they read as torch reads them, through the blend
prior, ``evaluate --checkpoint`` and ``train --init-from``; laid out by hand, every refusal issue 49 made
for zip archives (payloads, BUILD, bombs, deep nesting, sizes past the file) holds for them too."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
import torch

from cdm.checkpoint import load_checkpoint
from cdm.config import ModelConfig, load_config
from cdm.data import build_dataset
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.data.sample import collate
from cdm.diffusion import GaussianDiffusion
from cdm.evaluate import reconstruct
from cdm.io.torch import load_inert, load_tensors
from cdm.io.torch.archive import MAX_PICKLE_BYTES
from cdm.model import CDMNetwork
from cdm.prior_model import PriorNetwork, load_prior
from tests.conftest import tiny_config
from tests.hostile_files import assert_refused, run_command
from tests.hostile_torch import (
    GOOD_ID,
    LEGACY_ID,
    LITTLE_ENDIAN,
    MAGIC,
    PC2_FIRST_WEIGHT,
    legacy_file,
    long_list_pickle,
    nested_list_pickle,
    poisoning_pickle,
    reduce_call,
    tensor_pickle,
)
from tests.pc2_files import write_pc2_checkpoint
from tests.test_pc2_checkpoint import SMALL

RECORDS = {"0": struct.pack("<3f", 1.0, 2.0, 3.0)}
SETS = [arg for pair in SMALL for arg in ("--set", pair)]


def _legacy(obj, path: Path) -> Path:
    torch.save(obj, path, _use_new_zipfile_serialization=False)
    assert path.read_bytes()[:2] == b"\x80\x02"  # torch's pre-zip layout: pickles, not a zip archive
    return path


def _same(ours, theirs) -> bool:
    if isinstance(theirs, torch.Tensor):
        return type(ours) is type(theirs) and ours.dtype == theirs.dtype and torch.equal(ours, theirs) \
            and ours.stride() == theirs.stride() and ours.requires_grad == theirs.requires_grad
    if isinstance(theirs, dict):
        return type(ours) is type(theirs) and list(ours) == list(theirs) \
            and all(_same(ours[k], theirs[k]) for k in theirs)
    if isinstance(theirs, (list, tuple)):
        return type(ours) is type(theirs) and len(ours) == len(theirs) and all(map(_same, ours, theirs))
    return ours == theirs


def test_a_legacy_file_reads_as_torchs_own_loader_reads_it(tmp_path):
    base = torch.arange(12.0)
    linear = torch.nn.Linear(3, 2)
    obj = {"weights": base, "view": base[3:7], "transposed": base.view(3, 4).t(), "empty": torch.empty(0),
           "ints": torch.arange(5), "half": torch.ones(3, dtype=torch.float16), "bools": torch.tensor([True, False]),
           "state": linear.state_dict(), "parameter": torch.nn.Parameter(torch.ones(2)),
           "plain": [1, "x", None, (2.5, True)], "step": 7}
    path = _legacy(obj, tmp_path / "legacy.pt")
    theirs = torch.load(path, weights_only=False)  # the test's own file: torch's reader is the reference
    for read in (lambda: load_tensors(path, "x", "torch file", ""), lambda: load_inert(path, "x", "torch file")):
        ours = read()
        assert _same(ours, theirs)
        assert ours["view"].untyped_storage().data_ptr() == ours["weights"].untyped_storage().data_ptr()
        assert ours["view"].storage_offset() == 3 and ours["state"]._metadata == theirs["state"]._metadata


@pytest.mark.slow
def test_a_pvd_prior_in_the_legacy_format_blends_as_the_zip_one_does(tmp_path):
    """BDM's PVD priors were saved by torch 1.4: the same dict in both formats is the same prior."""
    network = PriorNetwork(ModelConfig(denoiser="pvcnn2", time_embed_dim=64))
    g = torch.Generator().manual_seed(7)
    weights = {f"model.module.{k}": torch.randn(v.shape, generator=g) * 0.01
               for k, v in network.denoiser.state_dict().items()}
    checkpoint = {"epoch": 1999, "model_state": weights, "optimizer_state": {}}
    torch.save(checkpoint, tmp_path / "zip.pth")
    _legacy(checkpoint, tmp_path / "legacy.pth")
    legacy, zipped = (load_prior(tmp_path / name, category="chair") for name in ("legacy.pth", "zip.pth"))
    assert _same(legacy.network.state_dict(), zipped.network.state_dict())
    first = "sa_layers.0.0.voxel_layers.0.weight"
    assert torch.equal(legacy.network.denoiser.state_dict()[first], weights[f"model.module.{first}"])

    cfg = tiny_config(tmp_path)
    batch = collate([build_dataset(cfg, "val")[0]])
    torch.manual_seed(0)
    cdm = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d]).eval()
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)

    def blended(name: str) -> torch.Tensor:
        sets = {"sampling.blend.enabled": True, "sampling.blend.prior_checkpoint": str(tmp_path / name),
                "sampling.blend.milestones": [936], "sampling.blend.select_prob": 1.0}
        return reconstruct(cdm, diffusion, batch, load_config(cfg.to_dict(), sets), torch.Generator().manual_seed(5))

    plain = reconstruct(cdm, diffusion, batch, cfg, torch.Generator().manual_seed(5))
    from_legacy = blended("legacy.pth")
    assert torch.equal(from_legacy, blended("zip.pth")) and not torch.equal(from_legacy, plain)


@pytest.mark.slow
def test_pc2s_checkpoint_in_the_legacy_format_evaluates_and_fine_tunes(tmp_path):
    path = tmp_path / "checkpoint-latest.pth"
    model = write_pc2_checkpoint(path, width=0.25, legacy=True)
    assert not path.read_bytes().startswith(b"PK")
    evaluated = run_command(["-m", "cdm", "evaluate", "--checkpoint", str(path), *SETS], tmp_path, timeout=300)
    assert evaluated.code == 0, evaluated.stderr[-2000:]
    assert evaluated.stdout.startswith(f"PC² checkpoint {path} (step 100000), trained on co3dv2 hydrant")
    scores = {line.split()[0]: float(line.split()[1]) for line in evaluated.stdout.splitlines()[3:]}
    assert 0 <= scores["eval/f1"] <= 1 and scores["eval/cd"] > 0
    extra = ["train.steps=1", "train.eval_every=1", "train.batch_size=2", "priors.render_size=32",
             "priors.num_views=1", f"train.out_dir={tmp_path / 'run'}"]
    trained = run_command(["-m", "cdm", "train", "--init-from", str(path), *SETS,
                           *[arg for pair in extra for arg in ("--set", pair)]], tmp_path, timeout=300)
    assert trained.code == 0 and "done at step 1" in trained.stdout, trained.stderr[-2000:]
    saved = load_checkpoint(tmp_path / "run" / "checkpoints" / "step_0000001")
    stem = "sa_layers.0.0.point_features.layers.0.weight"
    assert (saved.model[f"denoiser.{stem}"] - model[f"point_cloud_model.model.{stem}"]).abs().max() < 1e-2


def _past_the_cap() -> bytes:
    """A main pickle of one 17 MiB bytes object: the file's pickles outgrow :data:`MAX_PICKLE_BYTES`."""
    size = MAX_PICKLE_BYTES + 2**20
    return b"\x80\x02B" + struct.pack("<I", size) + bytes(size) + b"."


HUGE_ID = LEGACY_ID.replace(b"K\x03N", b"\x8a\x05" + (2**34).to_bytes(5, "little") + b"N")
"""Storage '0' declared as 2³⁴ floats (64 GiB) in a file of a few hundred bytes."""

CASES = {  # name: (main pickle, keyword arguments of legacy_file, what the refusal says)
    "deep": (nested_list_pickle(100_000), {}, "its pickle nests deeper than 100 levels"),
    "steps": (long_list_pickle(10**7), {}, "its pickle runs more than 2,000,000 steps"),
    "pickle_bomb": (_past_the_cap(), {}, f"its pickles take more than the {MAX_PICKLE_BYTES:,} bytes allowed"),
    "huge": (tensor_pickle(HUGE_ID), {"records": RECORDS},
             f"declares {2**36:,} bytes of tensors, more than the {8 * 2**30:,} allowed"),
    "past_end": (tensor_pickle(LEGACY_ID.replace(b"K\x03N", b"M\xe8\x03N")), {"records": RECORDS},
                 "its pickle declares 4,000 bytes of tensors; the file has"),
    "truncated": (tensor_pickle(LEGACY_ID), {"records": {"0": RECORDS["0"][:8]}, "counts": {"0": 3}},
                  "its storage '0' ends past the end of the file"),
    "count": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "counts": {"0": 5}},
              "its storage '0' gives 5 elements; the pickle says 12 bytes"),
    "trailing": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "tail": b"\x00"}, "bytes after its last storage"),
    "no_keys": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "keys": []}, "its storage key list does not match"),
    "twice": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "keys": ["0", "0"]}, "1 repeated"),
    "view": (tensor_pickle(LEGACY_ID.replace(b"K\x03N", b"K\x03(X\x01\x00\x00\x001K\x00K\x03t")),
             {"records": RECORDS}, "its pickle names a view of a storage"),
    "zip_id": (tensor_pickle(GOOD_ID), {"records": RECORDS},
               "torch.save writes ('storage', type, key, location, size, view)"),
    "past_tensor": (tensor_pickle(LEGACY_ID).replace(b"K\x03\x85K\x01", b"K\x04\x85K\x01"), {"records": RECORDS},
                    "reads a tensor past the end of its storage"),
    "magic": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "header": (1, 1001, LITTLE_ENDIAN)},
              "not in torch's file format"),
    "protocol": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "header": (MAGIC, 1000, LITTLE_ENDIAN)},
                 "a legacy torch file of protocol 1000; torch writes 1001"),
    "big_endian": (tensor_pickle(LEGACY_ID), {"records": RECORDS, "header": (
        MAGIC, 1001, {**LITTLE_ENDIAN, "little_endian": False})}, "written on a big-endian machine"),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_damaged_or_bomb_legacy_file_is_one_message_from_both_readers(tmp_path, name):
    pickled, layout, message = CASES[name]
    file = tmp_path / f"{name}.pt"
    legacy_file(file, pickled, **layout)
    for read in (lambda: load_inert(file, name, "torch file"), lambda: load_tensors(file, name, "torch file", "")):
        with pytest.raises(ValueError, match=f"^{name} is not a readable torch file: ") as refused:
            read()
        assert message in str(refused.value), str(refused.value)
    assert file.stat().st_size < (MAX_PICKLE_BYTES + 2**21 if name == "pickle_bomb" else 11 * 2**20)


def test_the_hand_laid_legacy_file_is_one_torch_itself_reads(tmp_path):
    """The layout the hostile cases break is torch's own: torch's loader reads the undamaged one."""
    legacy_file(tmp_path / "good.pt", tensor_pickle(LEGACY_ID), RECORDS)
    assert torch.load(tmp_path / "good.pt", weights_only=False)["w"].tolist() == [1.0, 2.0, 3.0]
    assert load_tensors(tmp_path / "good.pt", "x", "torch file", "")["w"].tolist() == [1.0, 2.0, 3.0]


def test_a_payload_or_a_build_in_a_legacy_file_runs_nothing(tmp_path):
    marker = tmp_path / "marker"
    legacy_file(tmp_path / "payload.pt", reduce_call("os.system", f"touch {marker}"))
    with pytest.raises(ValueError, match=r"payload\.pt could run code .*it calls os\.system\); refused"):
        load_inert(tmp_path / "payload.pt", "payload.pt", "torch file")
    with pytest.raises(ValueError, match=r"payload\.pt holds Python objects other than tensors .*it names os\.system"):
        load_tensors(tmp_path / "payload.pt", "payload.pt", "torch file", "")
    before = torch._utils._rebuild_tensor_v2.__defaults__
    legacy_file(tmp_path / "poison.pt", poisoning_pickle(LEGACY_ID), RECORDS)
    with pytest.raises(ValueError, match=r"it sets the state of torch\._utils\._rebuild_tensor_v2"):
        load_inert(tmp_path / "poison.pt", "poison.pt", "torch file")
    assert torch._utils._rebuild_tensor_v2.__defaults__ == before and not marker.exists()
    legacy_file(tmp_path / "header.pt", tensor_pickle(LEGACY_ID), RECORDS,
                header=(MAGIC, 1001, reduce_call("builtins.len", "ab")))
    with pytest.raises(ValueError, match=r"header\.pt holds Python objects .*it names builtins\.len"):
        load_tensors(tmp_path / "header.pt", "header.pt", "torch file", "")


@pytest.mark.slow
def test_hostile_legacy_files_are_one_line_through_the_commands_in_bounded_memory(tmp_path):
    marker = tmp_path / "marker"
    named = PC2_FIRST_WEIGHT.encode()  # so that evaluate and --init-from take it for PC²'s (read by load_inert)
    payload = b"\x80\x02}X" + struct.pack("<I", len(named)) + named + reduce_call("os.system", f"touch {marker}")[2:-1]
    files = {"payload": (payload + b"s.", {}, "could run code from the file while loading (it calls os.system)")}
    files.update({name: CASES[name] for name in ("huge", "past_end", "pickle_bomb", "deep")})
    baseline = run_command(["-c", "import torch, cdm.io.torch"], tmp_path).peak_rss
    for name, (pickled, layout, message) in files.items():
        file = tmp_path / f"{name}.pth"
        legacy_file(file, pickled, **layout)
        # PC²'s name makes evaluate read it (load_inert); any other 0.1.0 file is read by convert (load_tensors).
        command = ["evaluate", "--checkpoint", str(file), *SETS] if name == "payload" else [
            "convert", str(file), str(tmp_path / "converted")]
        outcome = run_command(["-m", "cdm", *command], tmp_path)
        assert_refused(outcome, f"checkpoint: {file}", message)
        assert outcome.peak_rss - baseline < 300 * 2**20, (name, outcome.peak_rss, baseline)
    outcome = run_command(["-m", "cdm", "train", "--init-from", str(tmp_path / "payload.pth"), *SETS], tmp_path)
    assert_refused(outcome, f"--init-from: {tmp_path / 'payload.pth'}", "(it calls os.system); refused")
    assert not marker.exists() and not (tmp_path / "runs").exists()
