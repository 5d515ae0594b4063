"""Estimate the paper's 2D depth prior on exported views: DINOv2's DPT head or Depth Anything.

The paper's depth prior comes from an estimator run on the input image (§3.3: DINOv2). This tool
runs one through Hugging Face ``transformers`` (an optional extra: ``pip install -e ".[depth]"``) on
the crops that ``python -m cdm.tools.export_views`` wrote and saves the maps in the layout
:mod:`cdm.data.depth_maps` reads::

    python -m cdm.tools.export_views --out views/ --set data.kind=co3d --set data.root=...
    python -m cdm.tools.estimate_depth --views views/ --model DIR_OR_HUB_ID --out depth_maps/

``--model`` is a local folder (``save_pretrained``'s layout: model and image-processor configs and
weights) or, on a machine that reaches the Hugging Face hub, a hub id such as
``facebook/dpt-dinov2-small-nyu`` or ``depth-anything/Depth-Anything-V2-Small-hf``. Nothing is
downloaded otherwise. On many views, ``python -m sweeps.inputs depth`` runs this as Ray tasks.

Output: ``<out>/<object_id>/<position>.npy``, float32 ``(H, W)`` of the crop ``<object_id>/<position>.png``
(same rows and columns: the model's output is resized back to the crop), and ``<out>/estimator.json``
naming the model and whether its maps hold **disparity** (larger = nearer). :class:`cdm.data.depth_maps.DepthMaps`
refuses a folder whose ``estimator.json`` disagrees with ``priors.depth_maps_disparity``. Which models
output what: Depth Anything's relative models and MiDaS-style DPT models output relative disparity;
DPT heads on a DINOv2 backbone (trained on NYU / KITTI) and Depth Anything's ``metric`` models output
depth. ``--predicts depth|disparity`` says it for other models. Maps already written are kept (resumable).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Literal, NamedTuple

import cv2
import numpy as np
import torch

from cdm.cli import add_out, command_parser
from cdm.data.depth_maps import ESTIMATOR_FILE
from cdm.interrupt import interruptible
from cdm.io.images import read_image
from cdm.io.json import read_json
from cdm.io.torch import load_tensors
from cdm.io.write import make_folder, write_atomic
from cdm.tools.export_views import crops

__all__ = [
    "Estimator", "View", "build_parser", "estimate", "find_views", "load_estimator", "main", "output_kind", "write_maps"
]


class View(NamedTuple):
    """One exported input crop: ``<views>/<object_id>/<position>.png``."""

    object_id: str
    position: int
    image: Path


class Estimator(NamedTuple):
    """A loaded depth model: the ``transformers`` model, its image processor, and what it outputs."""

    name: str
    model: torch.nn.Module
    processor: object
    disparity: bool
    device: torch.device


def output_kind(config) -> Literal["depth", "disparity"] | None:
    """What a ``transformers`` depth model's ``predicted_depth`` holds, from its config (module docstring);
    None where the config does not tell."""
    if config.model_type == "depth_anything":
        return "depth" if getattr(config, "depth_estimation_type", "relative") == "metric" else "disparity"
    if config.model_type == "dpt":
        backbone = getattr(config, "backbone_config", None)
        return "depth" if backbone is not None and backbone.model_type == "dinov2" else "disparity"
    return None


def load_estimator(model: str, device: str = "cpu", predicts: Literal["depth", "disparity"] | None = None) -> Estimator:
    """Load ``model`` (a local folder or a hub id) for inference on ``device``.

    Raises:
        ValueError: ``transformers`` missing, the model not loadable, or what it predicts unknown and
            ``predicts`` not given.
    """
    folder = Path(model).expanduser()
    for weights in sorted(folder.glob("*.bin")) if folder.is_dir() else ():
        # transformers reads these with torch's loader, whose refusal advises weights_only=False: ours first.
        load_tensors(weights, f"--model: {weights}", "weights file", "Pass the model's weights as safetensors")
    try:
        from transformers import AutoImageProcessor, AutoModelForDepthEstimation
        from transformers.utils import logging
    except ImportError:
        raise ValueError('--model: this tool needs transformers: pip install -e ".[depth]"') from None
    logging.set_verbosity_error()  # its notes on image back-ends and loading bars would bury this tool's own lines
    logging.disable_progress_bar()
    if model.startswith(("/", ".", "~")) and not Path(model).expanduser().is_dir():
        raise ValueError(f"--model: {model} is not a folder (a local model folder, or a hub id such as "
                         "facebook/dpt-dinov2-small-nyu)")
    try:
        net = AutoModelForDepthEstimation.from_pretrained(model)
        processor = AutoImageProcessor.from_pretrained(model)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--model: {model} is not a loadable depth model ({str(exc).splitlines()[0]})") from None
    kind = predicts or output_kind(net.config)
    if kind is None:
        raise ValueError(f"--predicts: {model} is a {net.config.model_type!r} model, which may predict depth or "
                         "disparity; say which: --predicts depth or --predicts disparity")
    return Estimator(model, net.to(device).eval(), processor, kind == "disparity", torch.device(device))


def find_views(views: Path) -> list[View]:
    """Every input crop of an ``export_views`` folder of a captured data set, by object and position: the
    objects its ``objects.json`` names, the crops ``<object_id>/<position>.png`` (ids hold slashes, e.g.
    ``co3d/teddybear/<sequence>``).

    Raises:
        ValueError: no ``objects.json``, an id that leads outside ``views``, or no crop at all.
    """
    index = views / "objects.json"
    if not index.is_file():
        raise ValueError(f"--views: {views} has no objects.json; write it with python -m cdm.tools.export_views")
    found = []
    ids = read_json(index, "--views")
    if not isinstance(ids, dict) or not all(isinstance(i, str) for i in ids):
        raise ValueError(f"--views: {index} is not export_views' record (object id → category)")
    for object_id in sorted(ids):
        folder = views / object_id
        if not folder.resolve().is_relative_to(views.resolve()):
            raise ValueError(f"--views: {index} names object {object_id!r}, a path outside {views}")
        found += [View(object_id, position, path) for position, path in crops(folder, "--views")]
    if not found:
        raise ValueError(f"--views: {views} holds no <object_id>/<position>.png crops; export_views writes them "
                         "for captured data sets (shapenet_r2n2, co3d)")
    return found


def _read_rgb(path: Path) -> np.ndarray:
    image = read_image(path, cv2.IMREAD_COLOR, "--views")
    if image is None:
        raise ValueError(f"--views: {path} is not a readable image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


@torch.inference_mode()
def estimate(estimator: Estimator, images: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Maps of a batch of ``(H, W, 3)`` uint8 RGB crops: ``(H, W)`` float32 each, row for row the crop's
    (the model's output, bicubically resized back), in the model's own units (``estimator.disparity``)."""
    inputs = estimator.processor(images=list(images), return_tensors="pt").to(estimator.device)
    predicted = estimator.model(**inputs).predicted_depth.float()  # (B, h, w)
    maps = []
    for image, one in zip(images, predicted):
        size = image.shape[:2]
        resized = torch.nn.functional.interpolate(one[None, None], size=size, mode="bicubic", align_corners=False)
        maps.append(resized[0, 0].cpu().numpy())
    return maps


def _save(out: Path, view: View, array: np.ndarray) -> None:
    """Write atomically, so a killed run leaves no half-written map under the final name."""
    path = make_folder(out / view.object_id, "--out") / f"{view.position}.npy"
    write_atomic(path, lambda f: np.save(f, array.astype(np.float32)), "--out", within=out)


def write_manifest(out: Path, name: str, disparity: bool) -> None:
    """``<out>/estimator.json``; ``ValueError`` if ``out`` already holds maps of another model or kind."""
    record = {"model": name, "disparity": disparity}
    path = make_folder(out, "--out") / ESTIMATOR_FILE
    if path.is_file() and not path.is_symlink():
        earlier = read_json(path, "--out")
        if earlier != record:
            earlier = earlier if isinstance(earlier, dict) else {}
            raise ValueError(f"--out: {out} holds maps of {earlier.get('model')!r} (disparity "
                             f"{earlier.get('disparity')}); choose another --out")
    write_atomic(path, json.dumps(record, indent=1), "--out")


def write_maps(estimator: Estimator, views: Sequence[View], out: Path, batch_size: int = 8,
               progress: bool = True) -> int:
    """Estimate and save the map of every view in ``views`` not yet in ``out``; returns maps written."""
    from tqdm import tqdm

    todo = [v for v in views if not (out / v.object_id / f"{v.position}.npy").is_file()]
    with tqdm(total=len(todo), desc="depth maps", unit="view", disable=not progress) as bar:
        for start in range(0, len(todo), batch_size):
            batch = todo[start:start + batch_size]
            for view, depth in zip(batch, estimate(estimator, [_read_rgb(v.image) for v in batch])):
                _save(out, view, depth)
            bar.update(len(batch))
    return len(todo)


def build_parser() -> argparse.ArgumentParser:
    p = command_parser("estimate-depth", __doc__.split("\n\n")[0],
                       "--views views/ --model depth-anything/Depth-Anything-V2-Small-hf --out depth_maps/")
    p.add_argument("--views", required=True, type=Path, metavar="DIR", help="output folder of cdm-lab export-views")
    p.add_argument("--model", required=True, metavar="DIR_OR_HUB_ID",
                   help="local model folder, or a hub id where the hub is reachable")
    add_out(p, "<object_id>/<position>.npy maps and estimator.json (priors.depth_maps)", required=True, type=Path)
    p.add_argument("--batch-size", type=int, default=8, metavar="N", help="crops per forward pass, >= 1 (default 8)")
    p.add_argument("--device", default=None, metavar="DEVICE",
                   help="torch device: cpu, cuda or cuda:N (default: cuda where available, else cpu)")
    p.add_argument("--predicts", choices=("depth", "disparity"),
                   help="what the model predicts, where its config does not tell (disparity: larger = nearer)")
    return p


@interruptible("cdm-lab estimate-depth")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    try:
        if args.batch_size < 1:
            raise ValueError("--batch-size must be >= 1")
        views = find_views(args.views)
        estimator = load_estimator(args.model, device, args.predicts)
        write_manifest(args.out, args.model, estimator.disparity)
        written = write_maps(estimator, views, args.out, args.batch_size)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {written} maps ({len(views) - written} already there) into {args.out}; run with "
          f"--set priors.depth_maps={args.out} --set priors.depth_maps_disparity={str(estimator.disparity).lower()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
