"""Write the per-object embeddings of supplementary Table 7 with OpenCLIP, on a machine that has it.

Not a dependency of CDM Lab (it downloads its weights): install ``open_clip_torch`` where you run
this, then copy the ``.npz`` files next to the data. Input: a folder from
``python -m cdm.tools.export_views`` (its ``objects.json`` names every object and category)::

    python -m cdm.tools.openclip_embeddings --views views/ --kind image --npz image.npz
    python -m cdm.tools.openclip_embeddings --views views/ --kind text  --npz text.npz
    python -m cdm.tools.openclip_embeddings --views views/ --kind depth --npz depth.npz

``image``: the embedding of the object's reference view (captured kinds: its lowest sequence
position, the held-out view for held-out objects; rendered kinds: round 0, view 0); ``text``: the
embedding of "a photo of a {category}"; ``depth``: the embedding of that view's depth map drawn as a
grey image (near = white), from ``<view>.depth.npy`` or an estimated map folder (``--depth-maps``).
Each entry is a unit-norm ``(E,)`` float32 vector under the object id (:mod:`cdm.model.embeddings`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from cdm.cli import command_parser
from cdm.interrupt import interruptible
from cdm.io.arrays import load_npy
from cdm.io.images import read_rgb
from cdm.io.json import read_json
from cdm.io.names import object_id_parts
from cdm.io.write import write_atomic
from cdm.tools.export_views import crops

__all__ = ["build_parser", "main"]


def _reference(folder: Path) -> Path:
    """The reference view's image of one object folder (module docstring)."""
    flat = crops(folder, "--views")
    return flat[0][1] if flat else folder / "0" / "0.png"


def _rgb(path: Path) -> np.ndarray:
    if (rgb := read_rgb(path, "--views")) is None:
        raise ValueError(f"--views: {path} is not an image")
    return rgb


def _depth_image(path: Path):
    from PIL import Image

    depth = load_npy(path, "--depth-maps")
    fg = depth > 0
    near = np.zeros_like(depth)
    if fg.any():
        lo, hi = depth[fg].min(), depth[fg].max()
        near[fg] = 1.0 if hi == lo else (hi - depth[fg]) / (hi - lo)
    return Image.fromarray((near * 255).astype(np.uint8)).convert("RGB")


def build_parser() -> argparse.ArgumentParser:
    p = command_parser("openclip-embeddings", __doc__.split("\n\n")[0], "--views views/ --kind image --npz image.npz")
    p.add_argument("--views", required=True, type=Path, metavar="DIR", help="output folder of cdm-lab export-views")
    p.add_argument("--kind", required=True, choices=("image", "text", "depth"),
                   help="what is embedded: the reference view, 'a photo of a {category}', or its depth drawn grey")
    p.add_argument("--npz", required=True, type=Path, metavar="FILE",
                   help="the embeddings to write: .npz, one unit-norm float32 vector per object id")
    p.add_argument("--depth-maps", type=Path, metavar="DIR",
                   help="estimated maps (<object_id>/<position>.npy) instead of rendered depth, with --kind depth")
    p.add_argument("--model", default="ViT-B-32", metavar="NAME", help="OpenCLIP model name (default ViT-B-32)")
    p.add_argument("--pretrained", default="laion2b_s34b_b79k", metavar="TAG",
                   help="OpenCLIP pretrained weights tag of --model (default laion2b_s34b_b79k)")
    return p


@interruptible("cdm-lab openclip-embeddings")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import open_clip  # optional: only where this script runs
    import torch
    from PIL import Image

    model, _, preprocess = open_clip.create_model_and_transforms(args.model, pretrained=args.pretrained)
    tokenizer = open_clip.get_tokenizer(args.model)
    model.eval()
    objects = read_json(args.views / "objects.json", "--views")
    for object_id in objects:  # ids become paths read below --views
        object_id_parts(object_id, f"--views: {args.views / 'objects.json'}")
    out = {}
    with torch.no_grad():
        for object_id, category in objects.items():
            if args.kind == "text":
                vector = model.encode_text(tokenizer([f"a photo of a {category}"]))[0]
            else:
                ref = _reference(args.views / object_id)
                if args.kind == "image":
                    picture = Image.fromarray(_rgb(ref))
                elif args.depth_maps is not None:
                    picture = _depth_image(args.depth_maps / object_id / f"{ref.stem}.npy")
                else:
                    picture = _depth_image(ref.with_name(f"{ref.stem}.depth.npy"))
                vector = model.encode_image(preprocess(picture)[None])[0]
            out[object_id] = (vector / vector.norm()).float().numpy()
    try:
        write_atomic(args.npz, lambda f: np.savez(f, **out), "--npz")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(out)} {args.kind} embeddings ({next(iter(out.values())).shape[0]} dims) to {args.npz}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
