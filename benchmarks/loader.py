"""Loader speed: samples per second from the published files vs from a prepared root, same objects.

Each pass is one cold epoch: every training object once (its view of round 0), with the process's
decode cache, the data set's record cache and the open-shard cache emptied first — what a large
data set costs when its objects no longer fit in memory. Files are in the page cache for both
variants. Images at the paper's 224², H = 10 prior views; Co3D frames at 960×720 or 640×880 JPEG
(Co3D's typical sizes), ShapeNet at R2N2's 137². Fixtures are the tests' (tests/datasets_fixtures.py).
Target (issue 7): the prepared root ≥ 5× faster.
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.common import paired
from cdm.config import load_config
from cdm.data import DATASETS, build_dataset
from cdm.data.cache import DECODED, read_shard
from cdm.data.prepare import prepare
from tests.datasets_fixtures import make_co3d, make_shapenet

__all__ = ["loader_speed"]


def _epoch(kind: str, root: Path, overrides: dict):
    cfg = load_config(
        None, {"data.kind": kind, "data.root": str(root), "data.image_size": 224, "priors.num_views": 10, **overrides}
    )
    dataset = build_dataset(cfg, "train")

    def run() -> None:
        DECODED.clear()
        read_shard.cache_clear()
        dataset._cache.clear()
        for index in range(len(dataset)):
            dataset.sample(index, 0)

    return run, len(dataset)


def loader_speed(quick: bool, out_dir: str) -> list[dict]:
    scratch = Path(out_dir) / "loader"
    per = 2 if quick else 4
    cases = [
        ("co3d", make_co3d(scratch / "co3d_raw", upscale=10, splits={"train": per, "val": 1}).root,
         {"data.num_points": 16384, "priors.prior_2d": "depth"}, "Co3D, 960×720 JPEG + mask + depth + PLY"),
        ("shapenet_r2n2", make_shapenet(scratch / "shapenet_raw", per_split={"train": per, "val": 1}).root,
         {"data.num_points": 4096, "priors.render_kind": "planar"}, "ShapeNet R2N2, 137² PNG + PC15k npy"),
    ]
    rows = []
    for kind, raw_root, overrides, label in cases:
        cfg = load_config(None, {"data.kind": kind, "data.root": str(raw_root), "data.image_size": 224, **overrides})
        prepared_root = prepare(DATASETS[kind], cfg, scratch / f"{kind}_prepared", progress=False).out
        prepared, count = _epoch(kind, prepared_root, overrides)
        raw, _ = _epoch(kind, raw_root, overrides)
        result = paired(prepared, raw, repeats=3 if quick else 7)
        rows.append(
            {
                "benchmark": "loader raw / prepared",
                "case": f"{label}: raw {count / result.b_s:.0f} vs prepared {count / result.a_s:.0f} samples/s "
                f"({count} objects)",
                "without_s": result.a_s / count,
                "with_s": result.b_s / count,
                "ratio": result.ratio,
                "target": ">= 5",
            }
        )
    return rows
