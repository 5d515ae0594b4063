"""Small external inputs written by tests: embeddings, generated condition images, depth maps.

Shared by the unit tests of each input and by the smoke sweeps of ``sweeps/global_features.yaml`` and
``sweeps/conditions.yaml`` (tests/integration/test_input_sweeps.py).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cdm.config import Config
from cdm.data import build_dataset


def object_ids(cfg: Config) -> list[str]:
    """Ids of every object of both splits of ``cfg`` (no rendering: ids only)."""
    return [ref.object_id for split in ("train", "val") for ref in build_dataset(cfg, split).objects]


def write_embeddings(
    path: Path, ids: list[str], shape: tuple[int, ...] = (12,), seed: int = 0
) -> dict[str, np.ndarray]:
    """One random float32 array of ``shape`` per id, as ``numpy.savez`` keyed by object id."""
    rng = np.random.default_rng(seed)
    arrays = {o: rng.standard_normal(shape).astype(np.float32) for o in ids}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return arrays


def write_condition_images(
    folder: Path, ids: list[str], views: int, size: int = 32, rounds: int = 1, seed: int = 0
) -> None:
    """``<id>/<round>/<view>.png`` for views ``0 … views``: a plain colour per image (view index in red)."""
    rng = np.random.default_rng(seed)
    for o in ids:
        for r in range(rounds):
            (folder / o / str(r)).mkdir(parents=True, exist_ok=True)
            for v in range(views + 1):
                colour = np.array([40 * v, *rng.integers(0, 256, 2)], dtype=np.uint8)  # RGB
                image = np.broadcast_to(colour, (size, size, 3))
                cv2.imwrite(
                    str(folder / o / str(r) / f"{v}.png"), cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
                )


def paper_inputs(folder: Path, depth_cfg: Config | None = None) -> Path:
    """``$CDM_INPUTS`` for the paper profile's dry runs: a placeholder for MSN's ViT-S/16 weights (a dry run
    checks that the file is there and reads none of it) and, given ``depth_cfg``, estimated depth maps of
    every object of its data set (:func:`tests.datasets_fixtures.write_depth_maps`)."""
    from tests.datasets_fixtures import write_depth_maps

    (folder / "msn").mkdir(parents=True)
    (folder / "msn" / "vits16_800ep.pth.tar").write_bytes(b"")
    if depth_cfg is not None:
        write_depth_maps(folder / "depth_maps", depth_cfg)
    return folder
