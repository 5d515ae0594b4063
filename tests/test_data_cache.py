"""Prepared roots (shards written atomically, resumable), the decode cache and data-loader workers."""

from __future__ import annotations

import os
import re

import pytest
import torch

from cdm.__main__ import main
from cdm.config import load_config
from cdm.data import build_dataset
from cdm.data.cache import DECODED, MANIFEST, SCRATCH, read_shard
from cdm.train import Trainer
from tests.conftest import tiny_config
from tests.datasets_fixtures import make_co3d, make_shapenet


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    base = tmp_path_factory.mktemp("raw")
    return {"shapenet_r2n2": make_shapenet(base / "shapenet", per_split={"train": 2, "val": 1}).root,
            "co3d": make_co3d(base / "co3d").root}


def _cfg(kind, root, size=48, **overrides):
    return load_config(
        None,
        {
            "data.kind": kind,
            "data.root": str(root),
            "data.image_size": size,
            "data.num_points": 512,
            "priors.num_views": 3,
            **overrides,
        },
    )


def _prepare(kind, root, out, size=48):
    return main(["prepare", "--set", f"data.kind={kind}", "--root", str(root), "--out", str(out),
                 "--set", f"data.image_size={size}"])


def _tensors(s):
    depth = [] if s.depth is None else [s.depth]
    cams = [
        s.camera.R,
        s.camera.T,
        s.camera.focal,
        s.camera.principal,
        s.view_cameras.R,
        s.view_cameras.T,
        s.view_cameras.focal,
    ]
    return [s.image, s.mask, s.prior_2d, s.points, *depth, *cams]


@pytest.mark.parametrize("kind", ["shapenet_r2n2", "co3d"])
def test_prepared_root_gives_the_same_samples_as_the_raw_files(trees, tmp_path, kind, capsys):
    out = tmp_path / "prepared"
    assert _prepare(kind, trees[kind], out) == 0
    assert f"--set data.kind={kind} --set data.root={out}" in capsys.readouterr().out
    for split in ("train", "val"):
        raw, prepared = build_dataset(_cfg(kind, trees[kind]), split), build_dataset(_cfg(kind, out), split)
        assert raw.objects == prepared.objects and prepared.prepared is not None
        for i in range(len(raw)):
            for round_ in range(2):
                a, b = raw.sample(i, round_), prepared.sample(i, round_)
                assert all(torch.equal(x, y) for x, y in zip(_tensors(a), _tensors(b), strict=True)), (
                    a.object_id,
                    round_,
                )


def test_prepared_root_serves_a_smaller_image_size_with_the_same_cameras(trees, tmp_path):
    out = tmp_path / "prepared"
    assert _prepare("co3d", trees["co3d"], out) == 0
    raw, prepared = build_dataset(_cfg("co3d", trees["co3d"], 24), "val"), build_dataset(_cfg("co3d", out, 24), "val")
    for i in range(len(raw)):
        a, b = raw[i], prepared[i]
        assert (
            b.image.shape == (3, 24, 24)
            and torch.equal(a.camera.R, b.camera.R)
            and torch.equal(a.camera.focal, b.camera.focal)
        )
        iou = (a.mask * b.mask).sum() / ((a.mask + b.mask) > 0).sum()
        assert iou > 0.85 and (a.image - b.image).abs().mean() < 0.08


def test_prepare_resumes_and_never_leaves_partial_files(trees, tmp_path, capsys):
    out = tmp_path / "prepared"
    assert _prepare("shapenet_r2n2", trees["shapenet_r2n2"], out) == 0
    shards = sorted(out.rglob("*.safetensors"))
    assert len(shards) == 6 and (out / MANIFEST).is_file()  # 2 categories × (2 train + 1 val)
    stamps = {p: p.stat().st_mtime_ns for p in shards}
    shards[0].unlink()
    stale = out / SCRATCH / f".{shards[1].name}.tmp-0123456789abcdef"  # what a killed run leaves behind
    stale.write_bytes(b"half")
    foreign = shards[1].with_name(".notes.tmp-2026")  # another program's file: not prepare's to remove
    foreign.write_bytes(b"mine")
    capsys.readouterr()
    assert _prepare("shapenet_r2n2", trees["shapenet_r2n2"], out) == 0
    assert "1 shards written, 5 already complete" in capsys.readouterr().out
    assert shards[0].is_file() and not stale.exists() and foreign.read_bytes() == b"mine"
    assert not list((out / SCRATCH).iterdir())
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items() if p != shards[0])
    # Another preparation into the same folder is refused rather than mixed in.
    assert _prepare("shapenet_r2n2", trees["shapenet_r2n2"], out, size=32) == 2
    assert f"--out: {out} holds a different preparation" in capsys.readouterr().err


def test_damaged_or_mismatched_prepared_roots_are_named(trees, tmp_path):
    out = tmp_path / "prepared"
    assert _prepare("co3d", trees["co3d"], out) == 0
    with pytest.raises(ValueError, match=r"data.kind: 'shapenet_r2n2', but .* was prepared from data.kind='co3d'"):
        build_dataset(_cfg("shapenet_r2n2", out), "train")
    with pytest.raises(ValueError, match="data.eval_split: .* prepared with splits"):
        build_dataset(_cfg("co3d", out, **{"data.eval_split": "test"}), "val")
    shard = min((out / "train").rglob("*.safetensors"))
    truncated = shard.with_name("cut.safetensors")
    truncated.write_bytes(shard.read_bytes()[:4000])
    with pytest.raises(ValueError, match=rf"^data.root: {re.escape(str(truncated))}: its tensors end at byte [0-9]+, "
                       r"the file at 4000 \(cut short.*rerun `python -m cdm prepare`$"):
        read_shard(truncated)
    shard.unlink()
    with pytest.raises(ValueError, match=r"incomplete: 1 of 4 shards missing .* run the same `python -m cdm prepare`"):
        build_dataset(_cfg("co3d", out), "train")


def test_decoded_views_are_shared_by_every_data_set_of_the_process(trees):
    DECODED.clear()
    first = build_dataset(_cfg("co3d", trees["co3d"]), "train")
    samples = [first.sample(i, 0) for i in range(len(first))]
    assert DECODED.misses == len(first) and DECODED.hits == 0
    # The next cell of a sweep builds its own data set (another point size, say): no image is decoded again.
    second = build_dataset(_cfg("co3d", trees["co3d"], **{"priors.point_size": 0.02}), "train")
    again = [second.sample(i, 0) for i in range(len(second))]
    assert DECODED.misses == len(first) and DECODED.hits == len(first)
    assert all(torch.equal(a.image, b.image) for a, b in zip(samples, again))


def test_data_loader_workers_give_the_same_batches(trees, tmp_path):
    cpus = len(os.sched_getaffinity(0))
    overrides = {"data.kind": "co3d", "data.root": str(trees["co3d"]), "data.categories": ["teddybear", "hydrant"],
                 "priors.prior_2d": "depth"}
    direct = Trainer(tiny_config(tmp_path / "a", **overrides))
    workers = Trainer(tiny_config(tmp_path / "b", **overrides, **{"data.num_workers": min(2, cpus)}))
    for step in range(3):
        a, b = direct.next_batch(), workers.next_batch()
        assert a.object_id == b.object_id and torch.equal(a.image, b.image) and torch.equal(a.depth, b.depth)
        assert torch.equal(a.view_cameras.R, b.view_cameras.R) and torch.equal(a.points, b.points)
        direct.step = workers.step = step + 1
    workers.step = 0  # a resume to another step restarts the loader there
    assert workers.next_batch().object_id == Trainer(tiny_config(tmp_path / "c", **overrides)).next_batch().object_id


def test_byte_lru_keeps_the_most_recent_values_within_its_budget():
    from cdm.data.lru import ByteLRU

    class Blob(bytes):
        def nbytes(self) -> int:
            return len(self)

    cache = ByteLRU(10)
    made = []

    def make(key: str, size: int):
        return lambda: made.append(key) or Blob(b"x" * size)

    cache.get("a", make("a", 4))
    cache.get("b", make("b", 4))
    assert cache.get("a", make("a", 4)) == b"xxxx"  # a hit: now b is the least recently used
    cache.get("c", make("c", 4))  # 12 bytes > 10: b goes
    assert (len(cache), cache.hits, cache.misses, made) == (2, 1, 3, ["a", "b", "c"])
    cache.get("b", make("b", 4))
    assert made[-1] == "b" and len(cache) == 2
    cache.get("big", make("big", 50))  # alone over the budget, the newest value still stays
    assert len(cache) == 1 and cache.get("big", make("big", 50)) and made.count("big") == 1
    cache.clear()
    assert (len(cache), cache.hits, cache.misses) == (0, 0, 0)


def test_a_root_prepared_in_the_per_object_box_frame_is_refused(tmp_path):
    import json

    from cdm.data.cache import FORMAT, PreparedRoot

    # Format 1 stored each object in its own bounding box; its clouds and cameras are not this frame's.
    (tmp_path / MANIFEST).write_text(json.dumps({"format": 1, "kind": "shapenet_r2n2", "categories": [], "splits": {}}))
    with pytest.raises(ValueError, match=rf"format 1, this version reads {FORMAT}; prepare again"):
        PreparedRoot.open(tmp_path, "shapenet_r2n2")


def test_a_prepared_root_naming_an_object_outside_it_is_refused(tmp_path):
    """A manifest's object ids become shard paths: one that climbs out is refused, not read."""
    import json

    from cdm.data.cache import FORMAT, MANIFEST, PreparedRoot

    escape = "co3d/teddybear/../../../../outside"
    (tmp_path / MANIFEST).write_text(json.dumps({"format": FORMAT, "kind": "co3d", "categories": ["teddybear"],
                                                 "splits": {"train": [["teddybear", escape]]}}))
    root = PreparedRoot.open(tmp_path, "co3d")
    with pytest.raises(
        ValueError, match=r"cdm_prepared.json, split 'train', category 'teddybear' names object 'co3d/teddybear/\.\./"
    ):
        root.objects("train", ("teddybear",))
