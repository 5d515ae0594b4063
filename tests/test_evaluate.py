"""Baselines against hand-computed cases; the evaluation set's fingerprint and per-object rows."""

from __future__ import annotations

import pytest
import torch

from cdm.baseline_names import BASELINES
from cdm.data import build_dataset
from cdm.evaluate import RetrievalBank, _category_medoids, baseline_clouds, build_eval_set
from cdm.metrics import chamfer_f1
from tests.conftest import tiny_config


def test_sphere_has_the_mean_radius_and_gaussian_the_per_axis_std():
    gen = torch.Generator().manual_seed(0)
    half = torch.nn.functional.normalize(torch.randn(2000, 3, generator=gen), dim=-1)
    directions = torch.cat([half, -half])  # symmetric: centred exactly at the origin
    radii = torch.where(torch.arange(2000) % 2 == 0, 1.0, 3.0).repeat(2)[:, None]  # half at radius 1, half at 3: mean 2
    gt = (directions * radii)[None]
    clouds = baseline_clouds(gt, ["mug"], {"mug": gt[0]}, gen)
    assert torch.allclose(clouds["sphere"].norm(dim=-1), torch.full((1, 4000), 2.0), atol=1e-5)
    stretched = gt * torch.tensor([1.0, 0.5, 0.1])
    gauss = baseline_clouds(stretched, ["mug"], {"mug": gt[0]}, gen)["gaussian"][0]
    assert torch.allclose(gauss.std(0), stretched[0].std(0), rtol=0.06)
    assert torch.allclose(gauss.mean(0), torch.zeros(3), atol=0.05)


def test_category_mean_is_the_chamfer_medoid(tmp_path):
    cfg = tiny_config(tmp_path)
    train = build_dataset(cfg, "train")
    medoids = _category_medoids(train, {"chair"}, cfg.eval.num_points, per_category=4)
    members = [train.surface(i).cloud for i, ref in enumerate(train.objects) if ref.category == "chair"][:4]
    n = min(cfg.eval.num_points, members[0].shape[0])
    totals = [sum(chamfer_f1(a[None, :n], b[None, :n]).cd.item() for b in members) for a in members]
    assert torch.equal(medoids["chair"], members[totals.index(min(totals))])


def test_retrieval_returns_the_cloud_of_the_nearest_silhouette():
    masks = torch.zeros(3, 1, 64, 64)
    masks[0, :, :32] = 1.0  # top half
    masks[1, :, :, :32] = 1.0  # left half
    masks[2, :, 16:48, 16:48] = 1.0  # centre square
    clouds = [torch.full((10, 3), float(k)) for k in range(3)]
    bank = RetrievalBank(torch.nn.functional.adaptive_avg_pool2d(masks, 32).flatten(1), clouds)
    query = masks[[2, 0]].clone()
    query[0, :, 16:20, 16:48] = 0.0  # a slightly smaller square is still nearest to the square
    got = bank.nearest(query)
    assert got.shape == (2, 10, 3)
    assert got[0].eq(2.0).all() and got[1].eq(0.0).all()


def test_eval_set_scores_every_baseline_per_object_and_fingerprints_the_objects(tmp_path):
    cfg = tiny_config(tmp_path, **{"eval.retrieval_bank": 3})
    val, train = build_dataset(cfg, "val"), build_dataset(cfg, "train")
    es = build_eval_set(cfg, val, train, cfg.eval.seed)
    ids = [oid for b in es.batches for oid in b.object_id]
    assert set(es.baseline_rows) == set(ids)
    for name in BASELINES:
        per_object = [es.baseline_rows[i][f"baseline/{name}/cd"] for i in ids]
        assert es.baseline_metrics[f"baseline/{name}/cd"] == pytest.approx(sum(per_object) / len(per_object))
    assert build_eval_set(cfg, val, train, cfg.eval.seed).fingerprint == es.fingerprint
    other = tiny_config(tmp_path, **{"eval.num_points": 64})
    assert build_eval_set(other, val, train, other.eval.seed).fingerprint != es.fingerprint


# --- eval.protocol ---------------------------------------------------------------------------------


def _shapenet_cfg(root, **extra):
    from cdm.config import load_config

    return load_config(None, {"data.kind": "shapenet_r2n2", "data.root": str(root), "data.image_size": 32,
                              "data.num_points": 512, "eval.num_points": 512, "priors.num_views": 2,
                              "train.batch_size": 2, **extra})


def test_paper_protocol_takes_every_object(tmp_path):
    from tests.datasets_fixtures import make_shapenet

    tree = make_shapenet(tmp_path / "sn", per_split={"train": 1, "val": 3, "test": 1})
    quick = _shapenet_cfg(tree.root, **{"eval.num_objects": 1})
    train, val = build_dataset(quick, "train"), build_dataset(quick, "val")
    assert sum(len(x) for x in build_eval_set(quick, val, train, 0).batches) == 2
    paper = _shapenet_cfg(tree.root, **{"eval.num_objects": 1, "eval.protocol": "paper"})
    every = build_eval_set(paper, val, train, 0)
    assert sum(len(x) for x in every.batches) == len(val) == 6


def test_one_drawn_object_per_category_and_drawing_changes_no_score(tmp_path):
    from cdm.data.priors2d import PRIOR_2D_CHANNELS
    from cdm.diffusion import GaussianDiffusion
    from cdm.evaluate import run_evaluation
    from cdm.model import CDMNetwork
    from sweeps.compare.plots import read_ply

    cfg = tiny_config(tmp_path, **{"data.categories": ["chair", "airplane"], "data.val_objects": 2,
                                   "eval.num_objects": 2, "eval.save_clouds": 8, "eval.retrieval_bank": 2})
    eval_set = build_eval_set(cfg, build_dataset(cfg, "val"), build_dataset(cfg, "train"), cfg.eval.seed)
    torch.manual_seed(0)
    network = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d])
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)
    drawn = run_evaluation(network, diffusion, eval_set, cfg, torch.device("cpu"), tmp_path / "eval")
    plain = run_evaluation(network, diffusion, eval_set, cfg, torch.device("cpu"), None)
    assert drawn.rows == plain.rows and drawn.metrics == plain.metrics
    ids = [str(r["object_id"]) for r in drawn.rows]
    firsts = {c: next(i for i, r in zip(ids, drawn.rows) if r["category"] == c) for c in ("chair", "airplane")}
    assert len(ids) == 4 and sorted(p.stem for p in tmp_path.joinpath("eval").glob("*.png")) == sorted(
        i.replace("/", "_") for i in firsts.values())
    for oid in firsts.values():
        stem = tmp_path / "eval" / oid.replace("/", "_")
        gt = next(b for b in eval_set.batches if oid in b.object_id)
        assert torch.allclose(
            torch.from_numpy(read_ply(stem.with_suffix(".gt.ply"))), gt.points[gt.object_id.index(oid)], atol=1e-6
        )
        for name in BASELINES:
            assert read_ply(stem.parent / f"{stem.name}.{name}.ply").shape[1] == 3
