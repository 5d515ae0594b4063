"""The per-sweep store of training views and evaluation sets (cdm/shared.py): runs read the same
tensors they would compute, so training and evaluation are bit-identical with or without it."""

from __future__ import annotations

import torch

from cdm.evaluate import build_eval_set
from cdm.metric_names import COMPUTE_METRIC
from cdm.shared import SharedStore, SharedViews, eval_key, rounds_needed, views_key
from cdm.train import Callback, Trainer, fit
from tests.conftest import tiny_config


class _Losses(Callback):
    def __init__(self):
        self.steps: list[dict[str, float]] = []
        self.evals: list[dict[str, float]] = []

    def on_step(self, step, metrics):
        self.steps.append({k: v for k, v in metrics.items() if k.startswith("train/loss")})

    def on_eval(self, step, metrics, files):
        self.evals.append({k: v for k, v in metrics.items() if k != COMPUTE_METRIC})  # a measured time: not repeatable


def test_rounds_cover_every_batch_of_the_run(tmp_path):
    cfg = tiny_config(tmp_path)
    trainer = Trainer(cfg)
    size = len(trainer.train_set)
    need = rounds_needed(cfg, size)
    from cdm.data.order import batch_indices

    seen = {epoch for step in range(cfg.train.steps) for epoch, _ in batch_indices(step, cfg.train.batch_size, size, 7)}
    assert seen == set(range(need))


def test_stored_samples_equal_rendered_ones(tmp_path):
    cfg = tiny_config(tmp_path)
    train = Trainer(cfg).train_set
    store = SharedStore(tmp_path / "shared")
    store.write_round(cfg, train, 1)
    views = SharedViews(store, cfg, train)
    for i in range(len(train)):
        a, b = views.sample(i, 1), train.sample(i, 1)
        for name in ("image", "mask", "depth", "prior_2d", "points"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.equal(a.view_cameras.R, b.view_cameras.R) and torch.equal(a.camera.focal, b.camera.focal)
        assert (a.category, a.object_id) == (b.category, b.object_id)
    # A round not in the store is rendered by the data set.
    assert torch.equal(views.sample(0, 2).image, train.sample(0, 2).image)


def test_condition_views_are_stored_too(tmp_path):
    cfg = tiny_config(tmp_path, **{"data.condition_views": 2, "data.condition_views_random": True})
    train = Trainer(cfg).train_set
    store = SharedStore(tmp_path / "shared")
    store.write_round(cfg, train, 0)
    a, b = SharedViews(store, cfg, train).sample(1, 0), train.sample(1, 0)
    assert torch.equal(a.conditions.image, b.conditions.image) and torch.equal(a.conditions.valid, b.conditions.valid)
    assert torch.equal(a.conditions.camera.R, b.conditions.camera.R)


def test_keys_follow_what_decides_the_content(tmp_path):
    cfg = tiny_config(tmp_path)
    t = Trainer(cfg)
    other_loss = cfg.replace(**{"priors.point_size": 0.08, "priors.lambda_3d": 0.5, "train.seed": 3})
    assert views_key(other_loss, t.train_set) == views_key(cfg, t.train_set)
    assert eval_key(other_loss, t.val_set, t.train_set) == eval_key(cfg, t.val_set, t.train_set)
    other_data = cfg.replace(**{"data.image_size": 16, "priors.render_size": 16})
    t2 = Trainer(other_data)
    assert views_key(other_data, t2.train_set) != views_key(cfg, t.train_set)
    other_2d = cfg.replace(**{"priors.prior_2d": "none"})
    assert views_key(other_2d, t.train_set) != views_key(cfg, t.train_set)
    other_eval = cfg.replace(**{"eval.num_points": 64})
    assert eval_key(other_eval, t.val_set, t.train_set) != eval_key(cfg, t.val_set, t.train_set)


def test_a_run_with_the_store_is_bit_identical(tmp_path):
    cfg = tiny_config(tmp_path, **{"train.steps": 20, "train.eval_every": 20})
    store = SharedStore(tmp_path / "shared")
    trainer = Trainer(cfg)
    for r in range(rounds_needed(cfg, len(trainer.train_set))):
        store.write_round(cfg, trainer.train_set, r)
    store.eval_set(cfg, trainer.val_set, trainer.train_set)  # stored by a first run, read by the next
    plain, shared = _Losses(), _Losses()
    fit(cfg.replace(**{"train.out_dir": str(tmp_path / "plain")}), [plain])
    fit(cfg.replace(**{"train.out_dir": str(tmp_path / "shared_run")}), [shared], shared=store)
    assert plain.steps == shared.steps and plain.steps
    assert plain.evals == shared.evals and plain.evals
    # The drawn objects' baseline clouds come back from the store too (the panels' PLY files).
    built = build_eval_set(cfg, trainer.val_set, trainer.train_set, cfg.eval.seed)
    read = store.eval_set(cfg, trainer.val_set, trainer.train_set)
    assert read.baseline_clouds.keys() == built.baseline_clouds.keys() and built.baseline_clouds
    assert all(
        torch.equal(read.baseline_clouds[o][b], c) for o, v in built.baseline_clouds.items() for b, c in v.items()
    )
    files = {p.name for p in (tmp_path / "shared_run").rglob("*.ply")}
    assert any(name.endswith(".gt.ply") for name in files) and any(name.endswith(".retrieval.ply") for name in files)
