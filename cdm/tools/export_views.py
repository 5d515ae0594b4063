"""Write the images a config's data set shows the model, named as the external inputs expect them.

Run your depth estimator, image generator or embedding model on these files and save the results
under the same names (layouts in :mod:`cdm.data.depth_maps`, :mod:`cdm.data.condition_images`,
:mod:`cdm.model.embeddings`)::

    python -m cdm.tools.export_views --out views/ [--rounds R] [--set data.kind=co3d --set data.root=...]

Captured kinds (``shapenet_r2n2``, ``co3d``): ``<object_id>/<position>.png`` (the input crop at
``data.image_size``, ``position`` its place in the sequence) and ``<position>.mask.png``.
Rendered kinds (``procedural``, ``meshes``): ``<object_id>/<round>/<view>.png`` for training rounds
``0 … R−1`` (held-out objects: round 0) and views ``0 … data.condition_views``, each with
``<view>.mask.png``, ``<view>.depth.npy`` (view depth, for depth-image embeddings) and
``<view>.points.png`` (a planar point rendering of the ground-truth cloud from that camera: what the
paper's ControlNet turns into an image). ``objects.json`` maps each object id to its category.
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from cdm.cli import add_out, add_set, command_parser
from cdm.config import load_config, parse_override
from cdm.interrupt import interruptible
from cdm.io.write import make_folder, write_atomic

__all__ = ["build_parser", "crops", "export_views", "main"]


def crops(folder: Path, label: str) -> list[tuple[int, Path]]:
    """``(position, path)`` of the crops ``<position>.png`` in ``folder``, by position; other names are
    not crops. A name of digits from another script (``².png``: ``str.isdigit`` takes it, ``int``
    refuses it) is refused, naming the file."""
    found = []
    for path in folder.glob("*.png"):
        if path.stem.isascii() and path.stem.isdigit():
            found.append((int(path.stem), path))
        elif path.stem.isdigit():
            raise ValueError(f"{label}: {path} is named with digits other than 0-9; crops are named "
                             "<position>.png with ASCII digits")
    return sorted(found)


def _write_png(path: Path, array: np.ndarray, out: Path) -> None:
    """``(S, S, 3)`` RGB or ``(S, S)`` uint8 as a PNG at ``path``, through the no-follow writer."""
    encoded = cv2.imencode(".png", cv2.cvtColor(array, cv2.COLOR_RGB2BGR) if array.ndim == 3 else array)[1]
    write_atomic(path, encoded.tobytes(), "--out", within=out)


def _png(path: Path, image: Tensor, out: Path) -> None:
    """``(C, S, S)`` in [0, 1] → 8-bit PNG (C = 1 or 3)."""
    array = (image.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    _write_png(path, array if array.shape[-1] == 3 else array[..., 0], out)


def export_views(cfg, out: Path, rounds: int = 1) -> int:
    """Write every object's views of ``cfg``'s training and held-out splits into ``out``; returns images written."""
    from cdm.data import build_dataset
    from cdm.data.captured import CapturedDataset
    from cdm.data.views import render_view
    from cdm.render import splat_points

    written, categories = 0, {}
    size = cfg.data.image_size
    for split in ("train", "val"):
        ds = build_dataset(cfg, split)
        for index, ref in enumerate(ds.objects):
            categories[ref.object_id] = ref.category
            folder = out / ref.object_id
            if isinstance(ds, CapturedDataset):
                record = ds.surface(index)
                make_folder(folder, "--out")
                for v, position in enumerate(record.views.tolist()):
                    view = ds.view(index, v)
                    _write_png(folder / f"{position}.png", view.image, out)
                    _write_png(folder / f"{position}.mask.png", view.mask, out)
                    written += 1
                continue
            surface = ds.surface(index)
            k = cfg.data.condition_views
            for r in range(rounds if split == "train" else 1):
                base = ds.drawn_view(index, r)
                make_folder(folder / str(r), "--out")
                for j in range(k + 1):
                    shot = render_view(surface, base._replace(azim=base.azim + 360.0 * j / (k + 1)), size, 1)
                    stem = folder / str(r) / str(j)
                    _png(stem.with_suffix(".png"), shot.image, out)
                    _png(stem.with_name(f"{j}.mask.png"), shot.mask, out)
                    write_atomic(stem.with_name(f"{j}.depth.npy"), partial(np.save, arr=shot.depth[0].numpy()), "--out",
                                 within=out)
                    points = splat_points(surface.cloud[None], shot.view_cameras, size, cfg.priors.point_size, "planar")
                    _png(stem.with_name(f"{j}.points.png"), points[:1], out)
                    written += 1
    write_atomic(make_folder(out, "--out") / "objects.json", json.dumps(categories, indent=1), "--out")
    return written


def build_parser() -> argparse.ArgumentParser:
    p = command_parser("export-views", __doc__.split("\n\n")[0],
                       "--out views/ --set data.kind=co3d --set data.root=prepared/")
    add_out(p, "<object_id>/<position>.png crops, masks and objects.json", required=True)
    p.add_argument("--config", metavar="FILE", help="YAML config (default: the built-in defaults)")
    add_set(p, "data.kind=co3d")
    p.add_argument("--rounds", type=int, default=1, metavar="R",
                   help="training view rounds to write, a count >= 1 (rendered kinds; default 1)")
    return p


@interruptible("cdm-lab export-views")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_config(args.config, dict(parse_override(s) for s in args.set))
        if args.rounds < 1:
            raise ValueError("--rounds must be >= 1")
        count = export_views(cfg, Path(args.out), args.rounds)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {count} views into {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
