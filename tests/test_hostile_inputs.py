"""Hostile data sets and files, each run through the command a user types (issue #43): exit 2, one
``error:`` line naming the file and the entry, no traceback, nothing written outside ``--out``, peak
memory under 1 GiB for the bombs, and no hang on a FIFO or ``/dev/zero`` (the subprocess timeout is the
guard: a hang would never return).

Each subprocess costs ~3 s of interpreter start; a few run in the fast tier, the rest are marked slow."""

from __future__ import annotations

import gzip
import json
import os
import shutil

import numpy as np
import pytest

from tests.datasets_fixtures import make_co3d, make_shapenet, write_depth_maps
from tests.hostile_files import assert_refused, gzip_bomb, nested_json, npy_header, run_command, write_npz

GIB = 2**30
HANG_GUARD_S = 60
"""A FIFO or /dev/zero read would never end; the command must be back well within this."""


def _co3d(tmp_path):
    root = tmp_path / "co3d"
    tree = make_co3d(root, categories=("teddybear",), frames=2, splits={"train": 1, "val": 1})
    return root, tree.sequences["teddybear"]["train"][0]


def _edit(path, edit):
    """Rewrite the (gzipped) JSON file ``path`` through ``edit(data)``."""
    gzipped = path.suffix == ".jgz"
    raw = path.read_bytes()
    data = json.loads(gzip.decompress(raw) if gzipped else raw)
    edit(data)
    text = json.dumps(data).encode()
    path.write_bytes(gzip.compress(text) if gzipped else text)


def _first_frame(key, value):
    def edit(entries):
        entries[0][key] = value
    return edit


def _prepare(root, tmp_path, kind="co3d", *extra, timeout=120, env=None):
    out = tmp_path / "a" / "out"
    out.parent.mkdir(parents=True, exist_ok=True)
    outcome = run_command(["-m", "cdm", "prepare", "--set", f"data.kind={kind}", "--root", str(root), "--out", str(out),
                           "--set", "data.image_size=32", *extra], tmp_path, timeout=timeout, env=env)
    return outcome, out


def _nothing_escaped(tmp_path, name):
    assert not list(tmp_path.rglob(f"{name}*")), list(tmp_path.rglob(f"{name}*"))
    assert not os.path.lexists(f"/{name}.safetensors")


# --- paths from annotations ---------------------------------------------------------------------------


def test_a_co3d_sequence_named_to_climb_out_of_out_writes_nothing(tmp_path):
    root, seq = _co3d(tmp_path)
    escape = "../../../../ESCAPED_CO3D"  # from out/train/co3d/teddybear/: lands beside out
    rename = lambda entries: [e.update(sequence_name=escape) for e in entries if e["sequence_name"] == seq]  # noqa: E731
    _edit(root / "teddybear" / "frame_annotations.jgz", rename)
    _edit(root / "teddybear" / "sequence_annotations.jgz", rename)
    _edit(root / "teddybear" / "set_lists" / "set_lists_fewview_dev.json",
          lambda lists: [e.__setitem__(0, escape) for e in lists["train"] if e[0] == seq])
    outcome, out = _prepare(root, tmp_path)
    assert_refused(outcome, "frame_annotations.jgz entry 0", "sequence_name", "ESCAPED_CO3D", "expected a plain name")
    _nothing_escaped(tmp_path, "ESCAPED_CO3D")
    assert not out.exists()


@pytest.mark.slow
def test_a_shapenet_model_named_to_climb_out_of_out_writes_nothing(tmp_path):
    root = tmp_path / "shapenet"
    tree = make_shapenet(
        root, per_split={"train": 2, "test": 1}, views=2, bdm_split=True, synsets={"chair": "03001627"}
    )
    model = tree.bdm_split["test"]["chair"][0]

    def rename(table):
        table["test"]["03001627"]["../../../../ESCAPED_SN"] = table["test"]["03001627"].pop(model)
    _edit(root / "pc_dict_v2.json", rename)
    outcome, out = _prepare(root, tmp_path, "shapenet_r2n2", "--set", "data.eval_split=test")
    assert_refused(outcome, "pc_dict_v2.json", "synset 03001627, model", "ESCAPED_SN", "expected a plain name")
    _nothing_escaped(tmp_path, "ESCAPED_SN")
    assert not out.exists()


@pytest.mark.slow
def test_a_co3d_image_path_outside_the_root_is_not_read(tmp_path):
    root, _ = _co3d(tmp_path)
    (tmp_path / "outside").mkdir()
    first = json.loads(gzip.decompress((root / "teddybear" / "frame_annotations.jgz").read_bytes()))[0]
    shutil.copy(root / first["image"]["path"], tmp_path / "outside" / "x.jpg")  # a readable image, were it read
    _edit(
        root / "teddybear" / "frame_annotations.jgz",
        _first_frame("image", {**first["image"], "path": "../outside/x.jpg"}),
    )
    outcome, out = _prepare(root, tmp_path)
    assert_refused(
        outcome,
        "frame_annotations.jgz entry 0: image.path gives the path '../outside/x.jpg', which leaves the data root",
    )
    assert not out.exists()


# --- memory from small files --------------------------------------------------------------------------


def test_a_gzip_bomb_of_annotations_is_refused_within_1_gib(tmp_path):
    root, _ = _co3d(tmp_path)
    assert gzip_bomb(root / "teddybear" / "frame_annotations.jgz", 3.0) < 4e6  # 3 GB of zeros in ~3 MB
    outcome, out = _prepare(root, tmp_path)
    assert_refused(outcome, "frame_annotations.jgz decompresses to more than 256 MiB", "CDM_MAX_ANNOTATION_MIB")
    assert outcome.peak_rss < GIB, outcome.peak_rss
    assert not out.exists()


@pytest.mark.slow
def test_the_annotation_cap_is_set_by_the_environment_and_named(tmp_path):
    root, _ = _co3d(tmp_path)
    gzip_bomb(root / "teddybear" / "frame_annotations.jgz", 0.2)
    outcome, _ = _prepare(root, tmp_path, env={"CDM_MAX_ANNOTATION_MIB": "16"})
    assert_refused(outcome, "decompresses to more than 16 MiB")
    assert outcome.peak_rss < GIB


@pytest.mark.slow
def test_an_npz_bomb_of_embeddings_is_refused_within_1_gib(tmp_path):
    from cdm.config import load_config
    from tests.input_fixtures import object_ids

    sets = {
        "data.train_objects": 1,
        "data.val_objects": 1,
        "data.categories": "[chair]",
        "model.global_feature": "concat",
        "model.global_source": "embeddings",
        "model.global_embeddings": str(tmp_path / "emb.npz"),
        "train.out_dir": str(tmp_path / "run"),
    }
    ids = object_ids(load_config(None, {k: (["chair"] if k == "data.categories" else v) for k, v in sets.items()}))
    size = write_npz(
        tmp_path / "emb.npz", {o: np.zeros(12, np.float32) for o in ids[1:]}, bomb=ids[0], bomb_gigabytes=1.7
    )
    assert size < 2e6
    outcome = run_command(
        ["-m", "cdm", "train", *[a for k, v in sets.items() for a in ("--set", f"{k}={v}")]], tmp_path
    )
    assert_refused(
        outcome, "model.global_embeddings", "emb.npz", "(1.6 GiB); an array read here may hold at most 512 MiB"
    )
    assert outcome.peak_rss < GIB, outcome.peak_rss


@pytest.mark.slow
def test_a_depth_map_whose_header_promises_37_gib_is_refused(tmp_path):
    from cdm.config import load_config

    root, _ = _co3d(tmp_path)
    maps = tmp_path / "maps"
    write_depth_maps(maps, load_config(None, {"data.kind": "co3d", "data.root": str(root), "data.image_size": 32}))
    lying = sorted(maps.rglob("*.npy"))[0]
    lying.write_bytes(npy_header((100_000, 100_000)))  # a header, no data
    outcome, _ = _prepare(root, tmp_path, "co3d", "--depth-maps", str(maps))
    assert_refused(outcome, f"priors.depth_maps: {lying} declares a float32 array of shape (100000, 100000) (37.3 GiB)")
    assert outcome.peak_rss < GIB


@pytest.mark.slow
@pytest.mark.parametrize(
    "focal,said",
    [
        ([2.2e5, 2.2e5], "must lie in [0.05, 50.0] (NDC)"),
        ([0, 0], "must lie in [0.05, 50.0]"),
        ([2.0, 0.5], "gives pixels 2.0× wider than high"),
        (["nan", 1], "must be 2 finite numbers"),
    ],
)
def test_co3d_intrinsics_out_of_range_are_refused_naming_the_entry(tmp_path, focal, said):
    root, _ = _co3d(tmp_path)
    focal = [float(f) for f in focal]

    def edit(entries):
        entries[1]["viewpoint"]["focal_length"] = focal
    _edit(root / "teddybear" / "frame_annotations.jgz", edit)
    outcome, _ = _prepare(root, tmp_path)
    assert_refused(outcome, "frame_annotations.jgz entry 1: viewpoint.focal_length", said)
    assert outcome.peak_rss < GIB


# --- malformed entries: one line, never a traceback --------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "key,value,said",
    [
        ("mask", [], "image, mask, depth and viewpoint must be objects"),
        ("mask", {"path": "teddybear/x.png", "mass": -1}, "mask.mass -1 must be a finite number ≥ 0"),
        ("depth", {"path": "teddybear/d.png", "scale_adjustment": 0}, "depth.scale_adjustment"),
        ("depth", {"path": "/etc/passwd"}, "depth.path gives the path '/etc/passwd', which leaves the data root"),
        (
            "image",
            {"path": "teddybear/x.jpg", "size": [10**6, 10]},
            "image.size [1000000, 10] must be two sides of 1 to 4096",
        ),
    ],
)
def test_co3d_mask_depth_and_image_entries_are_checked(tmp_path, key, value, said):
    root, _ = _co3d(tmp_path)
    _edit(root / "teddybear" / "frame_annotations.jgz", _first_frame(key, value))
    outcome, _ = _prepare(root, tmp_path)
    assert_refused(outcome, "frame_annotations.jgz entry 0", said)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["co3d", "shapenet_r2n2"])
def test_json_nested_100000_deep_is_refused_in_one_line(tmp_path, kind):
    if kind == "co3d":
        root, _ = _co3d(tmp_path)
        target = root / "teddybear" / "set_lists" / "set_lists_fewview_dev.json"
    else:
        root = tmp_path / "shapenet"
        make_shapenet(root, per_split={"train": 2, "test": 1}, views=2, bdm_split=True, synsets={"chair": "03001627"})
        target = root / "pc_dict_v2.json"
    target.write_text(nested_json(100_000))
    outcome, _ = _prepare(root, tmp_path, kind)
    assert_refused(outcome, f"{target} nests 100000 levels deep")


@pytest.mark.slow
def test_a_shapenet_split_file_that_is_not_utf8_is_named(tmp_path):
    root = tmp_path / "shapenet"
    make_shapenet(root, per_split={"train": 2, "test": 1}, views=2, bdm_split=True, synsets={"chair": "03001627"})
    (root / "pc_dict_v2.json").write_bytes(b'{"test": {"03001627": {"\xff\xfe": "test"}}}')
    outcome, _ = _prepare(root, tmp_path, "shapenet_r2n2", "--set", "data.eval_split=test")
    assert_refused(outcome, f"data.root: {root / 'pc_dict_v2.json'} is not JSON")


# --- not a regular file -------------------------------------------------------------------------------


def test_an_annotation_file_that_is_a_fifo_is_refused_not_waited_on(tmp_path):
    root, _ = _co3d(tmp_path)
    (root / "teddybear" / "frame_annotations.jgz").unlink()
    os.mkfifo(root / "teddybear" / "frame_annotations.jgz")  # nobody writes: a blocking open never returns
    outcome, _ = _prepare(root, tmp_path, timeout=HANG_GUARD_S)
    assert_refused(outcome, "frame_annotations.jgz is a FIFO; expected a regular file")


@pytest.mark.slow
@pytest.mark.parametrize("kind,said", [("fifo", "is a FIFO"), ("dev_zero", "is a character device")])
def test_a_checkpoint_that_is_a_fifo_or_dev_zero_is_refused_not_read(tmp_path, kind, said):
    path = tmp_path / "checkpoint.json"
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")  # read to the end, it would fill the memory
    outcome = run_command(["-m", "cdm", "evaluate", "--checkpoint", str(path)], tmp_path, timeout=HANG_GUARD_S)
    assert_refused(outcome, f"checkpoint: {path} {said}; expected a regular file")
    assert outcome.peak_rss < GIB


@pytest.mark.parametrize("kind,said", [("fifo", "is a FIFO"), ("dev_zero", "is a character device")])
def test_an_image_that_is_a_fifo_or_dev_zero_is_refused_not_read(tmp_path, kind, said):
    import cv2

    from cdm.io.images import read_image

    path = tmp_path / "frame000001.jpg"
    os.mkfifo(path) if kind == "fifo" else path.symlink_to("/dev/zero")
    with pytest.raises(ValueError, match=f"^data.root: {path} {said}; expected a regular file$"):
        read_image(path, cv2.IMREAD_COLOR, "data.root")


@pytest.mark.parametrize(
    "kind,said", [("folder", "is a folder"), ("fifo", "is a FIFO"), ("dev_zero", "is a character device")]
)
def test_a_reference_checkpoint_that_is_not_a_regular_file_is_refused_in_our_words(tmp_path, kind, said):
    from cdm.model import load_reference_checkpoint

    path = tmp_path / "pc2.pth"
    if kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")
    with pytest.raises(ValueError, match=f"^{path} {said}; expected a regular file$"):
        load_reference_checkpoint(path, "pc2")
