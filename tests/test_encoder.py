"""Tests of the frozen ViT-S/16 encoder (``model.encoder: vit_s16``) on random weights in MSN's layout."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from cdm.cameras import look_at_cameras, pixel_centers_ndc
from cdm.config import ConfigError
from cdm.model import CDMNetwork, FrozenViT, ViTS16, check_encoder_record, project_conditioning
from cdm.model.encoder import MSN_WEIGHTS_URL, load_msn_state_dict
from tests.conftest import tiny_config


def write_msn_checkpoint(path, seed: int = 0, *, module_prefix: bool = True):
    """Random ViT-S/16 weights saved as MSN publishes them: ``target_encoder`` with ``module.`` keys and an
    ``fc`` head."""
    torch.manual_seed(seed)
    vit = ViTS16()
    state = {k: torch.randn_like(v) * 0.05 for k, v in vit.state_dict().items()}
    for k in state:
        if k.endswith("norm1.weight") or k.endswith("norm2.weight") or k == "norm.weight":
            state[k] = 1.0 + state[k]
    prefix = "module." if module_prefix else ""
    encoder = {prefix + k: v for k, v in state.items()}
    encoder[prefix + "fc.fc1.weight"] = torch.randn(8, 384)  # MSN's projection head, which PC² drops
    torch.save({"target_encoder": encoder, "epoch": 800}, path)
    return state


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    path = tmp_path_factory.mktemp("vit") / "vits16_800ep.pth.tar"
    return path, write_msn_checkpoint(path)


def _reference_tokens(state, image):
    """Naive ViT-S/16: explicit per-patch embedding, per-head attention loops (no fused kernels)."""
    mean = torch.tensor((0.485, 0.456, 0.406)).view(3, 1, 1)
    std = torch.tensor((0.229, 0.224, 0.225)).view(3, 1, 1)
    x = (image - mean) / std
    s = image.shape[-1]
    g = s // 16
    patches = [x[:, 16 * i : 16 * i + 16, 16 * j : 16 * j + 16].reshape(-1) for i in range(g) for j in range(g)]
    w = state["patch_embed.proj.weight"].reshape(384, -1)
    tokens = torch.stack([w @ p + state["patch_embed.proj.bias"] for p in patches])
    pos = state["pos_embed"][0]
    grid = pos[1:].reshape(14, 14, 384).permute(2, 0, 1)[None]
    grid = F.interpolate(grid, size=(g, g), mode="bicubic", align_corners=False)[0].permute(1, 2, 0).reshape(-1, 384)
    h = torch.cat([state["cls_token"][0] + pos[:1], tokens + grid])
    ln = lambda v, n: F.layer_norm(v, (384,), state[f"{n}.weight"], state[f"{n}.bias"], eps=1e-6)  # noqa: E731
    for b in range(12):
        p = f"blocks.{b}."
        y = ln(h, p + "norm1") @ state[p + "attn.qkv.weight"].T + state[p + "attn.qkv.bias"]
        heads = []
        for head in range(6):
            q, k, v = (y[:, part * 384 + 64 * head : part * 384 + 64 * head + 64] for part in range(3))
            heads.append(torch.softmax(q @ k.T / math.sqrt(64), dim=-1) @ v)
        h = h + torch.cat(heads, dim=1) @ state[p + "attn.proj.weight"].T + state[p + "attn.proj.bias"]
        y = F.gelu(ln(h, p + "norm2") @ state[p + "mlp.fc1.weight"].T + state[p + "mlp.fc1.bias"])
        h = h + y @ state[p + "mlp.fc2.weight"].T + state[p + "mlp.fc2.bias"]
    return ln(h, "norm")[1:].T.reshape(384, g, g)


def test_vit_matches_a_naive_reference_and_upsamples_like_pc2(weights):
    path, state = weights
    encoder = FrozenViT(path)
    image = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    out = encoder(image, torch.ones(2, 1, 32, 32), torch.zeros(2, 0, 32, 32))
    assert out.shape == (2, 384, 32, 32)
    tokens = torch.stack([_reference_tokens(state, im) for im in image])
    assert torch.allclose(encoder.backbone((image - encoder.mean) / encoder.std), tokens, atol=1e-4)
    # Bilinear, align_corners=False: pixel p samples the token grid at (p + 0.5) / 16 - 0.5.
    expected = F.interpolate(tokens, size=(32, 32), mode="bilinear", align_corners=False)
    assert torch.allclose(out, expected, atol=1e-4)
    # Pixels 0..7 lie before the first patch centre (7.5): they carry patch (0, 0)'s token unblended.
    assert torch.allclose(out[:, :, 3, 5], tokens[:, :, 0, 0], atol=1e-4)


def test_pixel_to_point_mapping(weights):
    """A point projecting into pixel (r, c) receives the bilinear blend of the patch tokens at that pixel."""
    path, state = weights
    encoder = FrozenViT(path)
    s = 32
    image = torch.rand(1, 3, s, s, generator=torch.Generator().manual_seed(2))
    features = encoder(image, None, None)
    cams = look_at_cameras(torch.tensor([10.0]), torch.tensor([30.0]), torch.tensor([2.5]))
    centers = pixel_centers_ndc(s)  # (S, S, 2) NDC xy of each pixel centre
    tokens = _reference_tokens(state, image[0])
    for row, col in [(3, 5), (12, 20), (28, 9)]:
        x, y = centers[row, col]
        view = torch.stack([x * 2.5 / cams.focal[0], y * 2.5 / cams.focal[0], torch.tensor(2.5)])
        point = ((view - cams.T[0]) @ cams.R[0].T)[None, None]  # (1, 1, 3), projects to pixel (row, col)
        got = project_conditioning(features, point, cams, radius=0.01)[0, 0]
        fy, fx = (row + 0.5) / 16 - 0.5, (col + 0.5) / 16 - 0.5
        y0, x0 = math.floor(fy), math.floor(fx)
        blend = torch.zeros(384)
        for yy, wy in ((y0, 1 - (fy - y0)), (y0 + 1, fy - y0)):
            for xx, wx in ((x0, 1 - (fx - x0)), (x0 + 1, fx - x0)):
                blend += wy * wx * tokens[:, min(max(yy, 0), 1), min(max(xx, 0), 1)]
        assert torch.allclose(got, blend, atol=1e-4), (row, col)


def test_frozen_deterministic_cached_and_out_of_the_state_dict(weights):
    path, _ = weights
    encoder = FrozenViT(path).train()
    assert not encoder.backbone.training and not list(encoder.parameters()) and not encoder.state_dict()
    image = torch.rand(3, 3, 32, 32, generator=torch.Generator().manual_seed(3), requires_grad=True)
    first = encoder(image, None, None)
    assert not first.requires_grad
    again = encoder(image, None, None)  # from the cache
    uncached = FrozenViT(path, cache_bytes=0)(image, None, None)
    assert torch.equal(first, again) and torch.allclose(first, uncached, atol=1e-6)
    assert len(encoder._cache) == 3
    assert encoder.record == {"encoder": "vit_s16", "weights_sha256": encoder.record["weights_sha256"]}
    assert len(encoder.record["weights_sha256"]) == 64


def test_train_step_leaves_the_vit_unchanged_and_checkpoint_refuses_other_weights(weights, tmp_path):
    from cdm.checkpoint import load_checkpoint
    from cdm.train import Trainer

    path, _ = weights
    cfg = tiny_config(tmp_path, **{"model.encoder": "vit_s16", "model.encoder_weights": str(path),
                                   "model.feature_dim": 384, "train.steps": 1, "priors.num_views": 1})
    trainer = Trainer(cfg)
    before = {k: v.clone() for k, v in trainer.network.encoder.backbone.state_dict().items()}
    denoiser_before = trainer.network.denoiser.stem.weight.clone()
    trainer.train_step(trainer.next_batch())
    assert all(p.grad is None for p in trainer.network.encoder.backbone.parameters())
    assert not torch.equal(denoiser_before, trainer.network.denoiser.stem.weight)  # the step did train
    after = trainer.network.encoder.backbone.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    ckpt = trainer.save_checkpoint()
    state = load_checkpoint(ckpt)
    assert state.encoder["weights_sha256"] == trainer.network.encoder.record["weights_sha256"]
    assert not any(k.startswith("encoder.") for k in state.model)  # 22 M frozen weights are not copied
    other = tmp_path / "other.pth.tar"
    write_msn_checkpoint(other, seed=5)
    network = CDMNetwork(cfg.model.model_copy(update={"encoder_weights": str(other)}), 1)
    with pytest.raises(ValueError, match="model.encoder_weights: the checkpoint's frozen encoder"):
        check_encoder_record(state.encoder, network.encoder.record)
    with pytest.raises(ValueError, match="model.encoder: the checkpoint was trained with 'vit_s16'"):
        check_encoder_record(state.encoder, {"encoder": "cnn"})
    from cdm.checkpoint import load_network

    assert load_network(ckpt).network.encoder.record == state.encoder
    with pytest.raises(ValueError, match="model.encoder_weights: the checkpoint's frozen encoder"):
        load_network(ckpt, {"model.encoder_weights": str(other)})


def test_bad_weights_name_the_field(tmp_path, weights):
    with pytest.raises(ValueError, match=rf"model.encoder_weights: .*no such file; download .*{MSN_WEIGHTS_URL}"):
        load_msn_state_dict(tmp_path / "missing.pth")
    wrong_layout = tmp_path / "timm_renamed.pth"
    torch.save({"vit.patch_embed.weight": torch.zeros(384, 3, 16, 16)}, wrong_layout)
    with pytest.raises(ValueError, match="model.encoder_weights: .*not MSN's ViT-S/16 key layout"):
        load_msn_state_dict(wrong_layout)
    _, state = weights
    wide = dict(state, cls_token=torch.zeros(1, 1, 768))
    torch.save(wide, tmp_path / "vitb.pth")
    with pytest.raises(ValueError, match=r"model.encoder_weights: .*cls_token has shape \(1, 1, 768\)"):
        load_msn_state_dict(tmp_path / "vitb.pth")
    (tmp_path / "garbage.pth").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="model.encoder_weights: .*not a readable torch file"):
        load_msn_state_dict(tmp_path / "garbage.pth")
    plain = tmp_path / "plain.pth"
    torch.save(state, plain)  # a plain state dict with MSN's names also loads
    assert set(load_msn_state_dict(plain)) == set(state)


def test_config_requires_weights_and_384_channels(tmp_path):
    with pytest.raises(ConfigError, match="model.encoder_weights is required .*vits16_800ep.pth.tar"):
        tiny_config(tmp_path, **{"model.encoder": "vit_s16", "model.feature_dim": 384})
    with pytest.raises(ConfigError, match="model.feature_dim must be 384"):
        tiny_config(tmp_path, **{"model.encoder": "vit_s16", "model.encoder_weights": "w.pth"})
    with pytest.raises(ConfigError, match="data.image_size must be a multiple of 16"):
        tiny_config(tmp_path, **{"model.encoder": "vit_s16", "model.encoder_weights": "w.pth",
                                 "model.feature_dim": 384, "data.image_size": 40})


def test_cli_without_weights_file_exits_2_naming_the_field(tmp_path, capsys):
    from cdm.__main__ import main

    code = main(
        [
            "train",
            "--set",
            "model.encoder=vit_s16",
            "--set",
            "model.feature_dim=384",
            "--set",
            f"model.encoder_weights={tmp_path / 'none.pth'}",
            "--set",
            f"train.out_dir={tmp_path / 'run'}",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: model.encoder_weights:") and MSN_WEIGHTS_URL in err[-1]
    assert not (tmp_path / "run").exists()
