"""Held-out evaluation: sample reconstructions, score them, and score trivial baselines beside them.

A number without a baseline says little on small local runs (``benchmarks/RESULTS.md``, "Does the
quick config learn?": model and baselines side by side), so every evaluation also
scores, on the same objects and with the same metric:

- ``sphere``: points on a sphere centred at the origin with the ground truth's mean radius;
- ``gaussian``: an axis-aligned Gaussian with the ground truth's per-axis standard deviation;
- ``category_mean``: the category's mean training shape — the medoid (under Chamfer distance) of a
  few training clouds of that category. It knows the true category: an oracle.
- ``retrieval``: the cloud of the nearest training image, by L2 distance between the input
  silhouettes (masks, area-resampled to 32×32) over ``eval.retrieval_bank`` training images per
  category. Silhouettes rather than RGB because the embedded data set varies colour and lighting per
  image, which would dominate an RGB distance; it does not see the category.

Baselines are computed once per evaluation set (they do not depend on the model), per object, so a
cell can be compared with each of them pairwise on the same objects. Every cloud is scored in the data
set's frame as it is (:mod:`cdm.normalise`: BDM's units on ShapeNet, PC²'s on Co3D): no ground truth
rescales a prediction before it is scored.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cdm.baseline_names import BASELINES
from cdm.blend import blended_reconstruction
from cdm.cameras import Cameras, orbit_cameras, project_points
from cdm.config import F1_THRESHOLD, Config
from cdm.data.sample import Batch, collate
from cdm.data.views import ObjectDataset
from cdm.diffusion import GaussianDiffusion, SamplerSettings
from cdm.digest import json_digest
from cdm.io.write import make_folder, write_atomic
from cdm.metric_names import CD, F1, METRICS
from cdm.metrics import chamfer_f1, scores
from cdm.model import CDMNetwork
from cdm.normalise import FRAME_VERSION

__all__ = [
    "EvalOutput",
    "EvalSet",
    "RetrievalBank",
    "baseline_clouds",
    "build_eval_set",
    "reconstruct",
    "run_evaluation",
    "save_panel",
    "write_ply",
]

RETRIEVAL_SIZE = 32
"""Side of the resampled silhouettes the retrieval baseline compares, in pixels."""


@dataclass
class EvalSet:
    """The fixed objects every evaluation of a run (and every cell of a sweep) is scored on."""

    batches: list[Batch]
    fingerprint: str
    """Hash of the objects, their views and frame, and the scoring settings: equal fingerprints, comparable runs."""
    baseline_metrics: dict[str, float] = field(default_factory=dict)
    baseline_rows: dict[str, dict[str, float]] = field(default_factory=dict)
    """Per object id: ``{"baseline/<name>/cd": …, "baseline/<name>/f1": …}``."""
    baseline_clouds: dict[str, dict[str, Tensor]] = field(default_factory=dict)
    """The first object of each category (the drawn ones): baseline name → its ``(N, 3)`` cloud."""


@dataclass
class EvalOutput:
    """Metrics (``eval/cd``, ``eval/f1``, per category, baselines), per-object rows and written files."""

    metrics: dict[str, float]
    rows: list[dict[str, object]]
    files: list[Path]


def build_eval_set(cfg: Config, val: ObjectDataset, train: ObjectDataset, seed: int) -> EvalSet:
    """Take the held-out objects ``eval.protocol`` names (``quick``: the first ``eval.num_objects`` of each
    category; ``paper``: all of them) and score the baselines.

    ``train`` supplies the clouds for the category-mean oracle (up to 16 per category) and the
    retrieval baseline's bank.
    """
    per_cat: dict[str, list[int]] = {}
    limit = len(val.objects) if cfg.eval.protocol == "paper" else cfg.eval.num_objects
    for i, ref in enumerate(val.objects):
        if len(per_cat.setdefault(ref.category, [])) < limit:
            per_cat[ref.category].append(i)
    order = [i for cat in sorted(per_cat) for i in per_cat[cat]]
    chosen = [val[i] for i in order]
    bs = cfg.train.batch_size
    batches = [collate(chosen[i : i + bs]) for i in range(0, len(chosen), bs)]
    identity = {"data": [cfg.data.kind, cfg.data.root, cfg.data.seed, cfg.data.num_points, cfg.data.image_size],
                "objects": [s.object_id for s in chosen], "frame": FRAME_VERSION,
                "scoring": [cfg.eval.seed, cfg.eval.num_points, cfg.eval.f1_threshold]}
    eval_set = EvalSet(batches, json_digest(identity))
    means = _category_medoids(train, set(per_cat), cfg.eval.num_points)
    bank = RetrievalBank.build(train, set(per_cat), cfg.eval.retrieval_bank)
    gen = torch.Generator().manual_seed(seed)
    first_of = {cat: val.objects[idx[0]].object_id for cat, idx in per_cat.items()}
    scored: dict[str, list[tuple[str, dict[str, float]]]] = {name: [] for name in BASELINES}
    for batch in batches:
        clouds = {**baseline_clouds(batch.points, batch.category, means, gen), "retrieval": bank.nearest(batch.mask)}
        for j, (oid, cat) in enumerate(zip(batch.object_id, batch.category)):
            if oid == first_of[cat]:
                eval_set.baseline_clouds[oid] = {name: clouds[name][j].clone() for name in BASELINES}
        for name in BASELINES:
            m = _score(clouds[name], batch.points, cfg, gen)
            for j, (oid, cat) in enumerate(zip(batch.object_id, batch.category)):
                scored[name].append((cat, {k: v[j] for k, v in m.items()}))
                eval_set.baseline_rows.setdefault(oid, {}).update({f"baseline/{name}/{k}": v[j] for k, v in m.items()})
    for name, rows in scored.items():
        eval_set.baseline_metrics.update(_summarise(rows, f"baseline/{name}"))
    return eval_set


@dataclass
class RetrievalBank:
    """Training silhouettes and their clouds for the nearest-image baseline (category-blind)."""

    keys: Tensor
    """``(K, RETRIEVAL_SIZE²)`` resampled training masks."""
    clouds: list[Tensor]
    """The ``K`` training clouds, each ``(N, 3)``."""

    @classmethod
    def build(cls, train: ObjectDataset, categories: set[str], per_category: int) -> RetrievalBank:
        """The first ``per_category`` training objects of each category, each in its first view."""
        counts = dict.fromkeys(categories, 0)
        keys, clouds = [], []
        for i, ref in enumerate(train.objects):
            if ref.category in counts and counts[ref.category] < per_category:
                counts[ref.category] += 1
                sample = train.sample(i, 0)
                keys.append(_silhouette(sample.mask[None])[0])
                clouds.append(sample.points)
        return cls(torch.stack(keys), clouds)

    def nearest(self, masks: Tensor) -> Tensor:
        """For input masks ``(B, 1, H, W)``, the clouds ``(B, N, 3)`` of the nearest bank images."""
        idx = torch.cdist(_silhouette(masks), self.keys).argmin(dim=1)
        return torch.stack([self.clouds[int(i)] for i in idx])


def _silhouette(masks: Tensor) -> Tensor:
    return torch.nn.functional.adaptive_avg_pool2d(masks.float(), RETRIEVAL_SIZE).flatten(1)


def baseline_clouds(
    gt: Tensor, categories: Sequence[str], category_means: dict[str, Tensor], gen: torch.Generator
) -> dict[str, Tensor]:
    """Baseline predictions for a batch of GT clouds ``(B, N, 3)``; each value ``(B, N, 3)``."""
    b, n, _ = gt.shape
    centred = gt - gt.mean(1, keepdim=True)
    radius = centred.norm(dim=-1).mean(1)  # (B,)
    directions = torch.nn.functional.normalize(torch.randn(b, n, 3, generator=gen), dim=-1)
    std = centred.std(dim=1)  # (B, 3)
    gaussian = torch.randn(b, n, 3, generator=gen) * std[:, None, :]
    mean_shape = torch.stack([_resize(category_means[c], n, gen) for c in categories])
    return {"sphere": directions * radius[:, None, None], "gaussian": gaussian, "category_mean": mean_shape}


def _category_medoids(
    train: ObjectDataset, categories: set[str], num_points: int, per_category: int = 16
) -> dict[str, Tensor]:
    clouds: dict[str, list[Tensor]] = {c: [] for c in categories}
    for i, ref in enumerate(train.objects):
        if all(len(v) >= per_category for v in clouds.values()):
            break
        if ref.category in clouds and len(clouds[ref.category]) < per_category:
            clouds[ref.category].append(train.surface(i).cloud)  # no rendering: only the GT cloud is needed
    medoids = {}
    for cat, members in clouds.items():
        if not members:
            raise ValueError(f"data: category {cat!r} has held-out objects but no training objects")
        pts = torch.stack([m[: min(num_points, m.shape[0])] for m in members])  # (K, n, 3)
        k = pts.shape[0]
        left = pts.repeat_interleave(k, 0)
        right = pts.repeat(k, 1, 1)
        cd = chamfer_f1(left, right).cd.view(k, k)
        medoids[cat] = members[int(cd.sum(1).argmin())]
    return medoids


def _resize(cloud: Tensor, n: int, gen: torch.Generator) -> Tensor:
    idx = (
        torch.randint(cloud.shape[0], (n,), generator=gen)
        if cloud.shape[0] < n
        else torch.randperm(cloud.shape[0], generator=gen)[:n]
    )
    return cloud[idx]


def _subsample(cloud: Tensor, n: int, gen: torch.Generator) -> Tensor:
    """BDM samples a fixed number of points from each cloud before scoring; keep all if fewer."""
    if cloud.shape[1] <= n:
        return cloud
    idx = torch.randperm(cloud.shape[1], generator=gen)[:n]
    return cloud[:, idx.to(cloud.device)]


def _score(pred: Tensor, gt: Tensor, cfg: Config, gen: torch.Generator) -> dict[str, list[float]]:
    """BDM's protocol: ``eval.num_points`` from each cloud ``(B, N, 3)`` (the data set's frame, as given),
    then every declared metric (CD, F1 at ``eval.f1_threshold``, …) per shape."""
    return scores(
        _subsample(pred, cfg.eval.num_points, gen), _subsample(gt, cfg.eval.num_points, gen), cfg.eval.f1_threshold
    )


def _summarise(rows: list[tuple[str, dict[str, float]]], prefix: str) -> dict[str, float]:
    """Mean of each metric over ``(category, {metric: score})`` rows: ``<prefix>/<metric>[/<category>]``."""
    out = {f"{prefix}/{k}": float(np.mean([r[1][k] for r in rows])) for k in METRICS}
    for cat in sorted({r[0] for r in rows}):
        out.update({f"{prefix}/{k}/{cat}": float(np.mean([r[1][k] for r in rows if r[0] == cat])) for k in METRICS})
    return out


@torch.no_grad()
def reconstruct(
    network: CDMNetwork,
    diffusion: GaussianDiffusion,
    batch: Batch,
    cfg: Config,
    generator: torch.Generator,
    progress: Callable[[int, int], None] | None = None,
) -> Tensor:
    """Sample one reconstruction ``(B, N, 3)`` per input image of ``batch`` (already on the device).

    With ``sampling.blend.enabled``, BDM blending with the category priors (:mod:`cdm.blend`).
    """
    context = network.encode(batch)
    shape = (len(batch), cfg.data.num_points, 3)

    def model_fn(x: Tensor, t: Tensor) -> Tensor:
        return network(x, t, context, batch.camera)

    if cfg.sampling.blend.enabled:
        return blended_reconstruction(model_fn, diffusion, batch, cfg, generator, progress).points
    return diffusion.sample(model_fn, shape, SamplerSettings.from_config(cfg.diffusion),
                            generator=generator, device=batch.points.device, progress=progress)


def run_evaluation(
    network: CDMNetwork,
    diffusion: GaussianDiffusion,
    eval_set: EvalSet,
    cfg: Config,
    device: torch.device,
    out_dir: Path | None,
) -> EvalOutput:
    """Reconstruct every object of ``eval_set`` with a fixed seed and score it (CD ×1000, F1).

    Writes ``objects.csv`` (one row per object: ours and every baseline) into ``out_dir`` when given,
    and for the first object of each of the first ``eval.save_clouds`` categories a PNG panel and PLY
    clouds: ``<id>.ply`` (ours), ``<id>.gt.ply`` and ``<id>.<baseline>.ply``. Which objects are drawn
    never changes which are scored.
    """
    network.eval()
    sample_gen = torch.Generator(device=device).manual_seed(cfg.eval.seed)
    metric_gen = torch.Generator().manual_seed(cfg.eval.seed + 1)
    rows: list[dict[str, object]] = []
    files: list[Path] = []
    drawn: set[str] = set()
    for batch in eval_set.batches:
        batch_d = batch.to(device)
        pred = reconstruct(network, diffusion, batch_d, cfg, sample_gen).cpu()
        m = _score(pred, batch.points, cfg, metric_gen)
        for j in range(len(batch)):
            oid = batch.object_id[j]
            rows.append({"object_id": oid, "category": batch.category[j], "eval_set": eval_set.fingerprint,
                         **{k: v[j] for k, v in m.items()}, **eval_set.baseline_rows[oid]})
            category = batch.category[j]
            if out_dir is not None and category not in drawn and len(drawn) < cfg.eval.save_clouds:
                drawn.add(category)  # objects come grouped by category: this is its first one
                stem = oid.replace("/", "_")
                files.append(write_ply(out_dir / f"{stem}.ply", pred[j]))
                files.append(write_ply(out_dir / f"{stem}.gt.ply", batch.points[j]))
                files += [write_ply(out_dir / f"{stem}.{name}.ply", cloud)
                          for name, cloud in eval_set.baseline_clouds.get(oid, {}).items()]
                files.append(save_panel(out_dir / f"{stem}.png", batch, j, pred[j], m[CD.name][j], m[F1.name][j],
                                        cfg.eval.f1_threshold))
    network.train()
    metrics = _summarise([(str(r["category"]), {k: float(r[k]) for k in METRICS}) for r in rows], "eval")
    metrics.update(eval_set.baseline_metrics)
    if out_dir is not None:
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        table = make_folder(out_dir, "train.out_dir") / "objects.csv"
        write_atomic(table, text.getvalue(), "train.out_dir")
        files.append(table)
    return EvalOutput(metrics, rows, files)


def write_ply(path: Path, points: Tensor, label: str = "train.out_dir") -> Path:
    """Write an ``(N, 3)`` cloud as ASCII PLY (:func:`cdm.io.write.write_atomic`; ``label`` names the
    option that chose ``path`` in a refusal)."""
    make_folder(path.parent, label)
    pts = points.detach().cpu().numpy()
    header = (
        f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )

    def write(fh) -> None:
        fh.write(header.encode())
        np.savetxt(fh, pts, fmt="%.6f")

    write_atomic(path, write, label)
    return path


def save_panel(
    path: Path, batch: Batch, j: int, pred: Tensor, cd: float, f1: float, threshold: float = F1_THRESHOLD
) -> Path:
    """PNG of one object, two rows: the input image then the prediction from 3 views; the 2D prior then
    the ground truth from the same 3 views.

    Both clouds are centred on the ground truth's mean and seen from 3.5 times its radius (the frames'
    units differ by data set). Points are coloured by view depth (one scale per view for both clouds)
    and drawn far first, so the shape reads in 3D; sparser clouds get larger markers. Two rows of four
    keep each view about 300 px wide when MLflow's artifact pane scales the picture to its width.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cam: Cameras = batch.camera[j : j + 1]
    gt = batch.points[j].cpu()
    centre = gt.mean(0)
    radius = float((gt - centre).norm(dim=-1).max())
    elev = torch.tensor([20.0])
    views = orbit_cameras(elev, torch.tensor([30.0]), torch.tensor([3.5 * radius]), 3, focal=cam.focal)[0]
    fig, axes = plt.subplots(2, 4, figsize=(12, 6.4))
    axes[0, 0].imshow(batch.image[j].permute(1, 2, 0).cpu().numpy())
    axes[0, 0].set_title("input")
    prior = batch.prior_2d[j]
    axes[1, 0].imshow(prior[0].cpu().numpy() if prior.shape[0] else np.zeros(batch.image.shape[-2:]), cmap="gray")
    axes[1, 0].set_title("2D prior")
    for v in range(3):
        gt_depth = project_points((gt - centre)[None].float(), views[v : v + 1])[0, :, 2]
        near, far = float(gt_depth.min()), float(gt_depth.max())
        for row, (cloud, label) in enumerate([(pred, "prediction"), (gt, "ground truth")]):
            ax = axes[row, 1 + v]
            xyz = project_points((cloud.cpu() - centre)[None].float(), views[v : v + 1])[0]
            order = torch.argsort(xyz[:, 2], descending=True)
            xyz = xyz[order].numpy()
            ax.scatter(
                -xyz[:, 0],
                xyz[:, 1],
                s=min(12.0, max(1.5, 3000 / len(xyz))),
                c=xyz[:, 2],
                cmap="viridis",
                vmin=near,
                vmax=far,
                linewidths=0,
            )
            ax.set_xlim(-1, 1)
            ax.set_ylim(-1, 1)
            ax.set_title(f"{label}, view {v}")
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_aspect("equal")
    # F1's threshold is on the squared distance (cdm/metrics.py): its root in world units.
    fig.suptitle(f"{batch.object_id[j]}   CD×1000 {cd:.2f}   F1@{threshold:g} (sq. dist; {threshold ** 0.5:g} world) "
                 f"{f1:.3f}", fontsize=12)
    make_folder(path.parent, "train.out_dir")
    write_atomic(path, lambda fh: fig.savefig(fh, format="png", dpi=100, bbox_inches="tight"), "train.out_dir")
    plt.close(fig)
    return path
