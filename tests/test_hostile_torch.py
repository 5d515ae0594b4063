"""Hostile torch files through the commands a user types: nothing from the file runs, each refusal is one
``error:`` line naming the file, and a refused file costs bounded memory (issue 49, sections 1, 3 and 4)."""

from __future__ import annotations

import struct
import zipfile
from pathlib import Path

import pytest
import torch

from cdm.io.torch import load_inert, load_tensors
from tests.hostile_files import assert_refused, run_command
from tests.hostile_torch import (
    GOOD_ID,
    archive,
    long_list_pickle,
    nested_list_pickle,
    poisoning_pickle,
    saved,
    tensor_pickle,
    torchscript_archive,
)

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["data.image_size=32", "model.width_multiplier=0.25", "model.voxel_resolution_multiplier=0.25",
         "data.num_points=128", "train.threads=1"]
RECORDS = {"0": struct.pack("<3f", 1.0, 2.0, 3.0)}


def _sets(*pairs: str) -> list[str]:
    return [arg for pair in (*SMALL, *pairs) for arg in ("--set", pair)]


def _spec(folder: Path, name: str, base: str) -> Path:
    spec = folder / f"{name}.yaml"
    spec.write_text(f"name: {name}\nbase: {{{base}}}\ngrid: {{priors.point_size: [0.04]}}\n")
    return spec


@pytest.fixture
def evil(tmp_path: Path) -> tuple[Path, Path]:
    """A TorchScript archive that writes ``marker`` when torch reads it; proven so on a twin first."""
    control = tmp_path / "control-marker"
    torchscript_archive(tmp_path / "control.pth", control)
    torch.jit.load(str(tmp_path / "control.pth"))
    assert control.exists()  # the file kind is live: torch's own reader runs its code
    marker = tmp_path / "marker"
    torchscript_archive(tmp_path / "evil.pth", marker)
    return tmp_path / "evil.pth", marker


def _cdm_commands(evil: Path, image: Path) -> list[list[str]]:
    return [
        ["-m", "cdm", "evaluate", "--checkpoint", str(evil), *_sets()],
        ["-m", "cdm", "reconstruct", "--checkpoint", str(evil), "--image", str(image), "--ply", "c.ply", *_sets()],
        ["-m", "cdm", "train", "--init-from", str(evil), *_sets()],
    ]


@pytest.mark.slow
def test_a_torchscript_archive_runs_nothing_through_any_reader(evil, tmp_path):
    import cv2
    import numpy as np

    path, marker = evil
    image = tmp_path / "in.png"
    cv2.imwrite(str(image), np.full((32, 32, 3), 255, np.uint8))
    for args in _cdm_commands(path, image):
        assert_refused(run_command(args, tmp_path), str(path), "TorchScript archive")
    bases = {
        "prior": f"sampling.blend.enabled: true, sampling.blend.prior_checkpoint: {path}",
        "encoder": f"model.encoder: vit_s16, model.feature_dim: 384, model.encoder_weights: {path}",
        "init": f"model.init_from: {path}, model.denoiser: pvcnn2, model.encoder: vit_s16, model.feature_dim: 384",
    }
    for name, base in bases.items():
        spec = _spec(tmp_path, name, base)
        smoke = run_command([str(ROOT / "sweeps" / "run.py"), str(spec), "--smoke",
                             "--out", "res", "--tracking-uri", f"sqlite:///{tmp_path}/m.db"], tmp_path)
        assert_refused(smoke, str(path), "TorchScript archive")
        dry = run_command([str(ROOT / "sweeps" / "run.py"), str(spec), "--dry-run"], tmp_path)
        assert_refused(dry, str(path), "TorchScript archive")
    msn = tmp_path / "inputs" / "msn" / "vits16_800ep.pth.tar"
    msn.parent.mkdir(parents=True)
    msn.write_bytes(path.read_bytes())
    check = run_command([str(ROOT / "sweeps" / "inputs.py"), "all", "--set", "data.kind=co3d", "--root", "nowhere",
                         "--out", "prep", "--inputs", str(tmp_path / "inputs"), "--model", "dm"], tmp_path)
    assert_refused(check, str(msn), "TorchScript archive")
    assert not marker.exists()


def test_a_build_onto_torchs_rebuilder_is_refused_and_changes_nothing(tmp_path):
    before = torch._utils._rebuild_tensor_v2.__defaults__
    archive(tmp_path / "poison.pt", poisoning_pickle(), RECORDS)
    with pytest.raises(ValueError, match=r"poison\.pt could run code .*it sets the state of "
                                         r"torch\._utils\._rebuild_tensor_v2"):
        load_inert(tmp_path / "poison.pt", str(tmp_path / "poison.pt"), "torch file")
    with pytest.raises(ValueError, match=r"poison\.pt holds Python objects other than tensors"):
        load_tensors(tmp_path / "poison.pt", str(tmp_path / "poison.pt"), "torch file", "Pass weights.")
    assert torch._utils._rebuild_tensor_v2.__defaults__ == before
    torch.save({"w": torch.tensor([1.0, -2.0])}, tmp_path / "ok.pt")
    assert torch.load(tmp_path / "ok.pt", weights_only=True)["w"].tolist() == [1.0, -2.0]
    assert load_tensors(tmp_path / "ok.pt", "x", "y", "z")["w"].tolist() == [1.0, -2.0]


BAD_IDS = {
    "not a tuple": b"X\x03\x00\x00\x00abc",
    "wrong length": GOOD_ID[:-3] + b"t",
    "wrong type name": GOOD_ID.replace(b"storage", b"STORAGE"),
}


@pytest.mark.parametrize("what", sorted(BAD_IDS))
def test_a_bad_persistent_id_is_named_by_both_readers(tmp_path, what):
    file = tmp_path / "pid.pt"
    archive(file, tensor_pickle(BAD_IDS[what]), RECORDS)
    for read in (lambda: load_inert(file, f"x: {file}", "torch file"),
                 lambda: load_tensors(file, f"x: {file}", "torch file", "")):
        with pytest.raises(ValueError, match=r"^x: .*pid\.pt is not a readable torch file: its pickle names a "
                                             r"storage as .*; torch\.save writes \('storage', type, key"):
            read()


def test_reader_level_damage_is_one_message_each(tmp_path):
    cases = {
        "middle.pt": (tensor_pickle(GOOD_ID), RECORDS, "it gives byte order 'middle'; only 'little' or 'big'"),
        "deep.pt": (nested_list_pickle(100_000), {}, "its pickle nests deeper than 100 levels"),
        "short.pt": (tensor_pickle(GOOD_ID), {"0": b"\0" * 8}, "its storage '0' holds 8 bytes; the pickle says 12"),
        "past.pt": (tensor_pickle(GOOD_ID).replace(b"K\x03\x85K\x01", b"K\x04\x85K\x01"), RECORDS,
                    "reads a tensor past the end of its storage"),
    }
    for name, (pickled, records, message) in cases.items():
        file = tmp_path / name
        archive(file, pickled, records, byteorder="middle" if name == "middle.pt" else "little")
        for read in (lambda f=file, n=name: load_inert(f, n, "torch file"),
                     lambda f=file, n=name: load_tensors(f, n, "torch file", "")):
            with pytest.raises(ValueError, match=f"^{name} is not a readable torch file: .*") as refused:
                read()
            assert message in str(refused.value), (name, str(refused.value))
    big = saved({"w": torch.arange(4.0)})
    swapped = torch.arange(4.0).numpy().astype(">f4").tobytes()
    archive(tmp_path / "big.pt", big["data.pkl"], {"0": swapped}, byteorder="big")
    assert load_tensors(tmp_path / "big.pt", "x", "y", "z")["w"].tolist() == [0.0, 1.0, 2.0, 3.0]


@pytest.mark.slow
def test_bad_storage_references_are_one_line_through_evaluate_on_both_readers(tmp_path):
    from tests.hostile_torch import PC2_FIRST_WEIGHT

    # A file of ours from 0.1.0 is read (load_tensors) by convert alone; PC²'s (load_inert) by evaluate.
    for key, reader in (("w", "cdm 0.1.0 checkpoint"), (PC2_FIRST_WEIGHT, "PC² checkpoint")):
        for what, pid in BAD_IDS.items():
            file = tmp_path / f"{what.replace(' ', '_')}-{len(key)}.pt"
            archive(file, tensor_pickle(pid, key=key), RECORDS)
            outcome = run_command(_reading(file, key == "w", tmp_path), tmp_path)
            assert_refused(outcome, str(file), f"not a readable {reader}: its pickle names a storage as")
        file = tmp_path / f"middle-{len(key)}.pt"
        archive(file, tensor_pickle(GOOD_ID, key=key), RECORDS, byteorder="middle")
        outcome = run_command(_reading(file, key == "w", tmp_path), tmp_path)
        assert_refused(outcome, str(file), "it gives byte order 'middle'; only 'little' or 'big'")


def _reading(file: Path, ours: bool, folder: Path) -> list[str]:
    """The command that reads ``file``: ``convert`` for a 0.1.0 file of ours, ``evaluate`` for PC²'s."""
    if ours:
        return ["-m", "cdm", "convert", str(file), str(folder / "converted")]
    return ["-m", "cdm", "evaluate", "--checkpoint", str(file), *_sets()]


@pytest.mark.slow
def test_a_text_file_and_a_link_to_one_are_refused_through_evaluate(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("these are not weights\n")
    (tmp_path / "link.pt").symlink_to(text)
    for file in (text, tmp_path / "link.pt"):
        outcome = run_command(["-m", "cdm", "evaluate", "--checkpoint", str(file), *_sets()], tmp_path)
        assert_refused(outcome, str(file), "not in torch's file format")


@pytest.mark.slow
def test_a_deep_cfg_is_one_line_through_evaluate_and_train(tmp_path):
    from tests.hostile_torch import PC2_FIRST_WEIGHT

    deep = nested_list_pickle(100_000)
    pickled = b"\x80\x02}X" + struct.pack("<I", len(PC2_FIRST_WEIGHT)) + PC2_FIRST_WEIGHT.encode() + deep[2:-1] + b"s."
    archive(tmp_path / "deep.pth", pickled)
    for args in (["evaluate", "--checkpoint"], ["train", "--init-from"]):
        outcome = run_command(["-m", "cdm", *args, str(tmp_path / "deep.pth"), *_sets()], tmp_path)
        assert_refused(outcome, str(tmp_path / "deep.pth"), "nests deeper than 100 levels")


def _bombs(folder: Path) -> dict[str, Path]:
    """The issue's three: a 3 GiB data.pkl, a 10⁸-element list, a deflated 1 GiB storage record; and a list
    small enough for the size cap that only the step cap stops."""
    out = {name: folder / f"{name}.pt" for name in ("pickle", "list", "record")}
    out["steps"] = folder / "steps.pt"  # 10⁷ elements stored in 10 MB: under the size caps, over the step cap
    archive(out["steps"], long_list_pickle(10**7))
    _deflated_pickle(out["pickle"], 3 * 2**30)
    archive(out["list"], long_list_pickle(10**8), compress=zipfile.ZIP_DEFLATED)
    with zipfile.ZipFile(out["record"], "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("archive/data.pkl", tensor_pickle(GOOD_ID))
        with z.open("archive/data/0", "w", force_zip64=True) as member:
            for _ in range(64):
                member.write(bytes(2**24))
    return out


def _deflated_pickle(path: Path, size: int) -> None:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("archive/data.pkl", "w", force_zip64=True) as member:
            member.write(b"\x80\x02N.")
            for _ in range(size // 2**24):
                member.write(bytes(2**24))


@pytest.mark.slow
def test_the_three_bombs_are_refused_in_bounded_memory(tmp_path):
    baseline = run_command(["-c", "import torch, cdm.io.torch"], tmp_path).peak_rss
    for name, file in _bombs(tmp_path).items():
        outcome = run_command(_reading(file, True, tmp_path), tmp_path)
        assert_refused(outcome, str(file), "more than" if name != "steps" else "runs more than 2,000,000 steps")
        assert outcome.peak_rss - baseline < 300 * 2**20, (name, outcome.peak_rss, baseline)
        assert file.stat().st_size < (11 if name == "steps" else 4) * 2**20, name



@pytest.mark.slow
def test_a_depth_model_folder_with_pickled_objects_is_refused_in_our_words(tmp_path):
    import argparse

    import cv2
    import numpy as np

    model = tmp_path / "dpt"
    model.mkdir()
    torch.save({"w": argparse.Namespace(code=1)}, model / "pytorch_model.bin")
    views = tmp_path / "views"
    (views / "obj").mkdir(parents=True)
    (views / "objects.json").write_text('{"obj": "mug"}')
    cv2.imwrite(str(views / "obj" / "0.png"), np.full((32, 32, 3), 255, np.uint8))
    outcome = run_command(["-m", "cdm.tools.estimate_depth", "--views", str(views), "--model", str(model),
                           "--out", str(tmp_path / "out")], tmp_path)
    line = assert_refused(outcome, f"--model: {model / 'pytorch_model.bin'} holds Python objects", "safetensors")
    assert "weights_only" not in outcome.stderr, line
