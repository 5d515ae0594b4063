"""Per-object global embeddings as inputs (``model.global_source: embeddings``, supplementary Table 7)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cdm.config import ConfigError
from cdm.external_inputs import check_coverage, check_inputs
from cdm.model import CDMNetwork
from cdm.model.embeddings import load_embeddings
from tests.conftest import tiny_config
from tests.input_fixtures import object_ids, write_embeddings


def _cfg(tmp_path, path, feature="concat"):
    return tiny_config(tmp_path, **{"model.global_feature": feature, "model.global_source": "embeddings",
                                    "model.global_embeddings": str(path)})


@pytest.mark.parametrize("shape", [(12,), (3, 12)])
def test_network_reads_each_objects_embedding(tmp_path, shape):
    cfg = tiny_config(tmp_path)
    ids = object_ids(cfg)
    arrays = write_embeddings(tmp_path / "emb.npz", ids, shape)
    from cdm.data import build_dataset
    from cdm.data.sample import collate

    batch = collate([build_dataset(cfg, "val").sample(i) for i in range(2)])
    concat = CDMNetwork(_cfg(tmp_path, tmp_path / "emb.npz").model, 1)
    ctx = concat.encode(batch)
    expected = torch.stack([torch.from_numpy(np.atleast_2d(arrays[o])).mean(0) for o in batch.object_id])
    assert torch.equal(ctx.embedding, expected) and ctx.tokens is None
    assert concat.denoiser.in_channels == 8 + 1 + 5 + 12  # features + contour + RGB/mask/distance + E
    attend = CDMNetwork(_cfg(tmp_path, tmp_path / "emb.npz", "cross_attention").model, 1)
    ctx = attend.encode(batch)
    assert ctx.embedding is None and ctx.tokens.shape == (2, *np.atleast_2d(arrays[ids[0]]).shape)
    assert torch.equal(ctx.tokens[1], torch.from_numpy(np.atleast_2d(arrays[batch.object_id[1]])))
    out = attend(batch.points, torch.tensor([3, 7]), ctx, batch.camera)
    assert out.shape == batch.points.shape and torch.isfinite(out).all()


def test_embeddings_change_the_prediction_per_object(tmp_path):
    cfg = tiny_config(tmp_path)
    ids = object_ids(cfg)
    write_embeddings(tmp_path / "a.npz", ids, seed=0)
    write_embeddings(tmp_path / "b.npz", ids, seed=1)
    from cdm.data import build_dataset
    from cdm.data.sample import collate

    batch = collate([build_dataset(cfg, "val").sample(0)])
    outs = []
    for name in ("a", "b"):
        torch.manual_seed(0)
        net = CDMNetwork(_cfg(tmp_path, tmp_path / f"{name}.npz").model, 1)
        outs.append(net(batch.points, torch.tensor([5]), net.encode(batch), batch.camera))
    assert not torch.allclose(outs[0], outs[1])


def test_bad_embedding_files_name_the_field(tmp_path):
    ids = ["a", "b"]
    np.savez(tmp_path / "mixed.npz", a=np.zeros(4, np.float32), b=np.zeros(5, np.float32))
    with pytest.raises(ValueError, match=r"model.global_embeddings: every array must have the same shape"):
        load_embeddings(tmp_path / "mixed.npz")
    np.savez(tmp_path / "ints.npz", a=np.zeros(4, np.int64))
    with pytest.raises(ValueError, match="model.global_embeddings: the embedding of 'a' is not finite floating point"):
        load_embeddings(tmp_path / "ints.npz")
    np.save(tmp_path / "single.npy", np.zeros(4))
    with pytest.raises(ValueError, match="model.global_embeddings: .*single array, not an .npz"):
        load_embeddings(tmp_path / "single.npy")
    with pytest.raises(ValueError, match="model.global_embeddings: .* does not exist"):
        load_embeddings(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="model.global_embeddings: .* not an .npz"):
        load_embeddings(tmp_path / "junk.npz")
    emb = write_embeddings(tmp_path / "ok.npz", ids)
    assert set(load_embeddings(tmp_path / "ok.npz").tokens) == set(emb)
    with pytest.raises(ValueError, match="no embedding for object id 'c'"):
        load_embeddings(tmp_path / "ok.npz").batch(("a", "c"))


def test_missing_object_ids_and_paths_are_refused_before_training(tmp_path, capsys):
    cfg = tiny_config(tmp_path)
    ids = object_ids(cfg)
    write_embeddings(tmp_path / "part.npz", ids[:-1])
    bad = _cfg(tmp_path, tmp_path / "part.npz")
    from cdm.data import build_dataset

    with pytest.raises(ValueError, match=rf"model.global_embeddings: .* no embedding for object id '{ids[-1]}' \(1 of"):
        check_coverage(bad, (build_dataset(bad, "train"), build_dataset(bad, "val")))
    with pytest.raises(ValueError, match="model.global_embeddings: .*none.npz does not exist"):
        check_inputs(_cfg(tmp_path, tmp_path / "none.npz"))
    with pytest.raises(ConfigError, match="model.global_source=embeddings needs model.global_embeddings"):
        tiny_config(tmp_path, **{"model.global_source": "embeddings", "model.global_feature": "concat"})
    from cdm.__main__ import main

    code = main(
        [
            "train",
            "--set",
            "model.global_feature=concat",
            "--set",
            "model.global_source=embeddings",
            "--set",
            f"model.global_embeddings={tmp_path / 'part.npz'}",
            "--set",
            f"train.out_dir={tmp_path / 'run'}",
            "--set",
            "data.train_objects=6",
            "--set",
            "data.val_objects=2",
            "--set",
            "data.categories=[chair,mug]",
        ]
    )
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert code == 2 and len(err) == 1 and "model.global_embeddings" in err[0]
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("spec", "rows"), [("global_features", 6), ("conditions", 7)])
def test_each_cell_of_tables_7_and_8_is_one_paper_row_and_row_1_is_pc2(spec, rows):
    from pathlib import Path

    from sweeps.plan.spec import load_spec
    from sweeps.plan.trials import expand

    plan = expand(load_spec(Path(__file__).resolve().parent.parent / "sweeps" / f"{spec}.yaml"), "smoke")
    labels = [c.paper_label for c in plan.cells]
    assert len(set(labels)) == rows == len(plan.cells) and None not in labels
    assert all((c.config.priors.prior_3d, c.config.priors.prior_2d) == (False, "none") for c in plan.cells)  # PC² cells
    assert plan.cells[0].paper == {"eval/f1": 0.428}  # = PC² on teddybear, Table 3
