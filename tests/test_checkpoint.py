"""cdm.checkpoint: atomic save, typed load (weights only), and a network rebuilt from a checkpoint."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from cdm.checkpoint import CHECKPOINT_FILE, Checkpoint, load_checkpoint, load_network, save_checkpoint
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
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == [CHECKPOINT_FILE]
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
    torch.save({"config": {}, "step": 1}, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match="not a CDM checkpoint \\(missing model, voxel_backend\\)"):
        load_checkpoint(tmp_path / "partial.pt")
    with pytest.raises(ValueError, match="does not exist"):
        load_checkpoint(tmp_path / "nowhere")
