"""cdm.checkpoint: atomic save, typed load (weights only), and a network rebuilt from a checkpoint."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import safetensors.torch
import torch

from cdm.__main__ import main
from cdm.checkpoint import (
    CHECKPOINT_FILE,
    FORMAT,
    LEGACY_FILE,
    Checkpoint,
    load_checkpoint,
    load_network,
    save_checkpoint,
)
from cdm.data import build_dataset
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.data.sample import collate
from cdm.model import CDMNetwork


def _saved(tiny, folder, **fields) -> tuple[CDMNetwork, Checkpoint]:
    torch.manual_seed(0)
    network = CDMNetwork(tiny.model, PRIOR_2D_CHANNELS[tiny.priors.prior_2d], device="cpu")
    state = Checkpoint(
        config=tiny.to_dict(), step=3, voxel_backend=network.voxel_backend, model=network.state_dict(), **fields
    )
    save_checkpoint(state, folder)
    return network, state


def test_save_then_load_gives_the_same_typed_fields_and_leaves_no_temporary(tiny, tmp_path):
    _, state = _saved(tiny, tmp_path / "ck", torch_rng=torch.get_rng_state())
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == [CHECKPOINT_FILE, "model.safetensors",
                                                                   "training.safetensors"]
    loaded = load_checkpoint(tmp_path / "ck")
    assert isinstance(loaded, Checkpoint) and loaded.step == 3 and loaded.config == tiny.to_dict()
    assert loaded.kind is None and loaded.ema is None and torch.equal(loaded.torch_rng, state.torch_rng)
    assert all(torch.equal(loaded.model[k], v) for k, v in state.model.items())
    assert load_checkpoint(tmp_path / "ck" / CHECKPOINT_FILE).step == 3  # the file itself works too


def test_load_network_reproduces_the_saved_network_and_applies_overrides(tiny, tmp_path):
    network, _ = _saved(tiny, tmp_path / "ck")
    loaded = load_network(tmp_path / "ck", {"eval.num_objects": 2, "model.voxel_backend": "dense"})
    assert loaded.config.eval.num_objects == 2 and loaded.device == torch.device("cpu")
    assert loaded.network.voxel_backend == network.voxel_backend  # the trained back-end wins
    assert not loaded.network.training
    batch = collate([build_dataset(tiny, "train").sample(0)])
    x_t, t = torch.randn(1, tiny.data.num_points, 3, generator=torch.Generator().manual_seed(1)), torch.tensor([10])
    network.eval()
    with torch.no_grad():
        expected = network(x_t, t, network.encode(batch), batch.camera)
        got = loaded.network(x_t, t, loaded.network.encode(batch), batch.camera)
    assert torch.equal(got, expected)


def test_ema_weights_are_the_ones_evaluated(tiny, tmp_path):
    network, state = _saved(tiny, tmp_path / "plain")
    ema = {k: v + 1.0 if v.is_floating_point() else v for k, v in state.model.items()}
    save_checkpoint(dataclasses.replace(state, ema=ema), tmp_path / "ema")
    loaded = load_network(tmp_path / "ema").network.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in ema.items())


def test_bad_checkpoints_are_clear_errors(tiny, tmp_path):
    _saved(tiny, tmp_path / "prior", kind="category_prior", category="chair")
    with pytest.raises(ValueError, match=r"checkpoint: .* holds a category_prior \(chair\), not a CDM network"):
        load_network(tmp_path / "prior")
    (tmp_path / "partial").mkdir()
    (tmp_path / "partial" / CHECKPOINT_FILE).write_text(json.dumps({"format": FORMAT, "config": {}, "step": 1}))
    with pytest.raises(ValueError, match="not a CDM checkpoint \\(missing model, voxel_backend\\)"):
        load_checkpoint(tmp_path / "partial")
    with pytest.raises(ValueError, match="does not exist"):
        load_checkpoint(tmp_path / "nowhere")


def _same(a, b) -> bool:
    """Equal values of equal types all the way down; tensors bit-exact with dtype and shape."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape and torch.equal(
            a.reshape(-1).view(torch.uint8), b.reshape(-1).view(torch.uint8))
    if isinstance(a, dict):
        return type(a) is type(b) and list(a) == list(b) and all(_same(v, b[k]) for k, v in a.items())
    if isinstance(a, list | tuple):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and (a == b or a != a and b != b)


def _plain(value, name):
    """A state dict (an ``OrderedDict``) as the plain dict read back, in its order; other fields as they are."""
    return dict(value) if name in ("model", "ema") else value


def _trained(tiny) -> Checkpoint:
    """A training checkpoint of two real steps with EMA and AdamW state, and a loss scale as fp16 keeps it."""
    from cdm.train import Trainer
    from tests.conftest import tiny_config

    trainer = Trainer(tiny_config(Path(tiny.train.out_dir).parent, **{"train.ema_decay": 0.9}))
    for _ in range(2):
        trainer.train_step(trainer.next_batch())
    scale = {"scale": 65536.0, "growth_factor": 2.0, "backoff_factor": 0.5, "growth_interval": 2000,
             "_growth_tracker": 1}
    return dataclasses.replace(trainer.state(), loss_scale=scale)


def test_every_field_of_a_training_checkpoint_round_trips_bit_exact(tiny, tmp_path):
    state = _trained(tiny)
    assert state.ema is not None and state.optimizer["state"] and isinstance(state.optimizer["state"], dict)
    save_checkpoint(state, tmp_path / "ck")
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == [
        CHECKPOINT_FILE, "ema.safetensors", "model.safetensors", "training.safetensors"]
    loaded = load_checkpoint(tmp_path / "ck")
    for field in dataclasses.fields(Checkpoint):
        assert _same(*(_plain(getattr(c, field.name), field.name) for c in (state, loaded))), field.name
    assert isinstance(loaded.optimizer["param_groups"][0]["betas"], tuple)  # AdamW's own types, keys ints
    assert set(loaded.optimizer["state"]) == set(range(len(state.optimizer["state"])))


def test_the_weights_load_with_safetensors_alone_and_inference_checkpoints_hold_no_training_state(tiny, tmp_path):
    state = _trained(tiny)
    save_checkpoint(state.for_inference(), tmp_path / "model")
    assert sorted(p.name for p in (tmp_path / "model").iterdir()) == [CHECKPOINT_FILE, "ema.safetensors",
                                                                      "model.safetensors"]
    for name in ("model", "ema"):
        plain = safetensors.torch.load_file(tmp_path / "model" / f"{name}.safetensors")
        assert _same(dict(sorted(plain.items())), dict(sorted(getattr(state, name).items())))
    assert list(load_checkpoint(tmp_path / "model").model) == list(state.model)  # the state dict's order kept
    record = json.loads((tmp_path / "model" / CHECKPOINT_FILE).read_text())
    assert record["training"] is None and record["optimizer"] is None and record["step"] == 2
    # A training checkpoint saved over it again and then an inference one: no stale training file is left.
    save_checkpoint(state, tmp_path / "model")
    save_checkpoint(state.for_inference(), tmp_path / "model")
    assert not (tmp_path / "model" / "training.safetensors").exists()
    assert load_network(tmp_path / "model").config.train.out_dir == type(tiny.train)().out_dir


def _legacy(state: Checkpoint, folder):
    """What cdm 0.1.0 wrote: one torch.save of the checkpoint's fields."""
    folder.mkdir(parents=True)
    torch.save({f.name: getattr(state, f.name) for f in dataclasses.fields(state)}, folder / LEGACY_FILE)
    return folder


def test_a_0_1_0_checkpoint_is_refused_with_the_way_out_and_converts_bit_exact(tiny, tmp_path, capsys):
    state = _trained(tiny)
    old = _legacy(state, tmp_path / "old")
    for path in (old, old / LEGACY_FILE):
        with pytest.raises(ValueError, match=rf"checkpoint: .*old/{LEGACY_FILE} was written by cdm 0\.1\.0 "
                                             r"\(torch\.save\); convert it once with `cdm-lab convert "):
            load_checkpoint(path)
    assert main(["convert", str(old), str(tmp_path / "new")]) == 0
    assert f"{tmp_path / 'new'}" in capsys.readouterr().out
    loaded = load_checkpoint(tmp_path / "new")
    assert all(_same(_plain(getattr(state, f.name), f.name), _plain(getattr(loaded, f.name), f.name))
               for f in dataclasses.fields(Checkpoint))
    assert main(["convert", str(old), str(tmp_path / "new")]) == 2  # nothing converted over a checkpoint
    assert capsys.readouterr().err == f"error: NEW: {tmp_path / 'new'} holds a checkpoint already; name an empty or " \
                                      "new folder\n"
    assert main(["convert", str(tmp_path / "new"), str(tmp_path / "again")]) == 2  # not a 0.1.0 file
    assert capsys.readouterr().err == f"error: checkpoint: {tmp_path / 'new' / LEGACY_FILE} does not exist\n"
    assert not (tmp_path / "again").exists()


def test_training_resumed_from_a_converted_0_1_0_checkpoint_continues_identically(tmp_path):
    from cdm.checkpoint import convert_legacy
    from cdm.train import Callback, fit
    from tests.conftest import tiny_config

    class Losses(Callback):
        def __init__(self):
            self.steps, self.checkpoints = {}, []

        def on_step(self, step, metrics):
            self.steps[step] = metrics["train/loss"]

        def on_checkpoint(self, step, path):
            self.checkpoints.append((step, path))

    settings = {"train.steps": 4, "train.eval_every": 2, "train.log_every": 1}
    full = Losses()
    fit(tiny_config(tmp_path / "full", **settings), [full])
    two = next(p for s, p in full.checkpoints if s == 2)
    old = _legacy(load_checkpoint(two), tmp_path / "old")
    convert_legacy(old, tmp_path / "converted")
    resumed = Losses()
    fit(tiny_config(tmp_path / "again", **settings), [resumed], resume_from=tmp_path / "converted")
    assert sorted(resumed.steps) == [3, 4] and all(resumed.steps[s] == full.steps[s] for s in (3, 4))
