"""Image encoders: per-pixel feature maps that projection conditioning lifts onto points.

- :class:`ImageEncoder` (``model.encoder: cnn``) — a small trainable CNN over RGB, mask and the
  2D-prior channels (Eq. 7), our default, cheap enough for a laptop.
- :class:`FrozenViT` (``model.encoder: vit_s16``) — PC²'s encoder: a frozen ViT-S/16 with MSN weights
  (384 channels), read from a **local** file (``model.encoder_weights``; nothing is downloaded).

Both map ``image (B, 3, S, S)``, ``mask (B, 1, S, S)``, ``prior_2d (B, C2, S, S)`` to
``(B, out_channels, S, S)`` in the pixel layout of :mod:`cdm.cameras`, and expose ``out_channels``
and ``record`` (what a checkpoint stores to refuse other weights, :func:`check_encoder_record`).

How PC² uses the ViT (its ``experiments/model/feature_model.py``): ImageNet mean/std normalisation,
timm's ``VisionTransformer`` with ``global_pool=''``, i.e. every token after the final LayerNorm;
the CLS token is dropped, the ``(S/16)²`` patch tokens are laid out row-major as a ``(384, S/16,
S/16)`` grid and upsampled bilinearly (``align_corners=False``) to ``S × S``. So the feature of
patch ``(i, j)`` sits at pixel centre ``(16 i + 7.5, 16 j + 7.5)``; at other pixels it is blended
with its neighbours. The position embedding is resized bicubically when ``S ≠ 224`` (timm's
``resize_pos_embed``). The published MSN file (``vits16_800ep.pth.tar``) holds the weights under
``target_encoder`` with a ``module.`` prefix and a projection head ``fc.*`` that PC² drops.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from cdm.config import ModelConfig
from cdm.data.lru import ByteLRU
from cdm.io.files import file_sha256
from cdm.io.torch import load_inert
from cdm.model.state_dicts import checked_state_dict
from cdm.model.voxels import norm_groups
from cdm.paths import input_path

__all__ = [
    "MSN_WEIGHTS_URL",
    "VIT_S16_CHANNELS",
    "FrozenViT",
    "ImageEncoder",
    "ViTS16",
    "build_encoder",
    "check_encoder_record",
    "load_msn_state_dict",
    "upsample_features",
]

MSN_WEIGHTS_URL = "https://dl.fbaipublicfiles.com/msn/vits16_800ep.pth.tar"
"""Where PC² takes its ViT-S/16 weights (facebookresearch/msn); download once, pass the local path."""
VIT_S16_CHANNELS = 384
"""Channels of a ViT-S/16 token (PC²'s feature dimension)."""
_PATCH, _DEPTH, _HEADS, _MLP = 16, 12, 6, 4
_PC2_PREFIX = "feature_model.model."  # PC²'s FeatureModel holds timm's VisionTransformer as `model`
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


def _conv_block(in_channels: int, out_channels: int, stride: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1),
        nn.GroupNorm(norm_groups(out_channels), out_channels),
        nn.SiLU(),
    )


class ImageEncoder(nn.Module):
    """Trainable CNN: ``[RGB, mask, 2D prior]`` → per-pixel features ``(B, feature_dim, S, S)``.

    Works at S/4 (two stride-2 convolutions of ``feature_dim`` and ``2·feature_dim`` channels and one
    more 3×3 convolution there, receptive field ≈ 15 px), merges with the S/2 map, projects to
    ``feature_dim`` and upsamples bilinearly to ``S`` — cheap enough to run every training step.

    Args:
        prior_2d_channels: ``C2``, channels of the 2D prior (0 for none, 1 for contour or depth).
        feature_dim: output channels (``model.feature_dim``).
    """

    record = {"encoder": "cnn"}

    def __init__(self, prior_2d_channels: int, feature_dim: int):
        super().__init__()
        if prior_2d_channels < 0 or feature_dim < 1:
            raise ValueError("prior_2d_channels must be >= 0 and model.feature_dim >= 1")
        self.prior_2d_channels = prior_2d_channels
        self.out_channels = feature_dim
        wide = 2 * feature_dim
        self.down1 = _conv_block(4 + prior_2d_channels, feature_dim, stride=2)
        self.down2 = _conv_block(feature_dim, wide, stride=2)
        self.mid = _conv_block(wide, wide, stride=1)
        self.out = nn.Conv2d(wide + feature_dim, feature_dim, 1)

    def forward(self, image: Tensor, mask: Tensor, prior_2d: Tensor) -> Tensor:
        """``(B, 3, S, S)`` RGB in [0, 1], ``(B, 1, S, S)`` mask, ``(B, C2, S, S)`` prior → ``(B, F, S, S)``."""
        return upsample_features(self.coarse(image, mask, prior_2d), image.shape[-1])

    def coarse(self, image: Tensor, mask: Tensor, prior_2d: Tensor) -> Tensor:
        """:meth:`forward` before its last bilinear upsampling: ``(B, F, ⌈S/2⌉, ⌈S/2⌉)``."""
        if prior_2d.shape[1] != self.prior_2d_channels:
            raise ValueError(
                f"prior_2d has {prior_2d.shape[1]} channels but the encoder was built for {self.prior_2d_channels}"
            )
        half = self.down1(torch.cat([image, mask, prior_2d], dim=1))
        quarter = self.mid(self.down2(half))
        # out(cat[upsample(quarter), half]), computed as upsample(W_q·quarter) + W_h·half + b: the 1×1
        # convolution is linear and bilinear weights sum to 1, so it commutes with the upsampling, which
        # then moves F channels, not 2F, and no concatenation is made (the same function; float rounding).
        wide = quarter.shape[1]
        weight = self.out.weight
        up = F.interpolate(F.conv2d(quarter, weight[:, :wide]), size=half.shape[-2:], mode="bilinear",
                           align_corners=False)
        return up + F.conv2d(half, weight[:, wide:], self.out.bias)


class _Attention(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(x).view(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)  # (B, heads, N, C / heads)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class _Block(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = _Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = _Mlp(dim, _MLP * dim)

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class _PatchEmbed(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, _PATCH, stride=_PATCH)


class ViTS16(nn.Module):
    """ViT-S/16 (12 blocks, 6 heads, 384 channels, pre-norm, LayerNorm ε 1e-6) with MSN/timm/DeiT
    parameter names: ``patch_embed.proj``, ``cls_token``, ``pos_embed`` ``(1, 197, 384)``,
    ``blocks.{i}.{norm1,attn.qkv,attn.proj,norm2,mlp.fc1,mlp.fc2}``, ``norm``."""

    def __init__(self):
        super().__init__()
        dim = VIT_S16_CHANNELS
        self.patch_embed = _PatchEmbed(dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + (224 // _PATCH) ** 2, dim))
        self.blocks = nn.ModuleList(_Block(dim, _HEADS) for _ in range(_DEPTH))
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def _pos_embed(self, grid: int) -> Tensor:
        cls, patches = self.pos_embed[:, :1], self.pos_embed[:, 1:]
        side = math.isqrt(patches.shape[1])
        if side == grid:
            return self.pos_embed
        patches = patches.reshape(1, side, side, -1).permute(0, 3, 1, 2)
        patches = F.interpolate(patches, size=(grid, grid), mode="bicubic", align_corners=False)
        return torch.cat([cls, patches.permute(0, 2, 3, 1).reshape(1, grid * grid, -1)], dim=1)

    def forward(self, image: Tensor) -> Tensor:
        """``(B, 3, S, S)`` ImageNet-normalised RGB, ``S`` a multiple of 16 → patch tokens
        ``(B, 384, S/16, S/16)`` after the final LayerNorm (row-major patch order, CLS dropped)."""
        b, _, s, _ = image.shape
        grid = s // _PATCH
        x = self.patch_embed.proj(image).flatten(2).transpose(1, 2)  # (B, grid², 384)
        x = torch.cat([self.cls_token.expand(b, -1, -1), x], dim=1) + self._pos_embed(grid)
        for block in self.blocks:
            x = block(x)
        x = self.norm(x)[:, 1:]
        return x.transpose(1, 2).reshape(b, -1, grid, grid)


def load_msn_state_dict(path: str | Path, name: str = "model.encoder_weights") -> dict[str, Tensor]:
    """The ViT-S/16 state dict of a local weights file, validated against :class:`ViTS16`'s layout.

    Accepts MSN's published checkpoint (``{"target_encoder": {"module.<name>": tensor, ...}, ...}``,
    the projection head ``fc.*`` dropped as PC² does), a plain state dict with the same names, or PC²'s
    checkpoint, which saves the frozen ViT with the rest of its model under ``feature_model.model.``
    (timm's names, which are MSN's; its pickled config is read as data, :func:`cdm.io.torch.load_inert`).

    Raises:
        ValueError: missing file, unreadable file, a key that is not a string, a weight that is not a finite
            tensor (:func:`cdm.model.state_dicts.checked_state_dict`), missing/unexpected keys or wrong shapes; the
            message names the config field ``name`` that gave the file.
    """
    path = input_path(path)
    field = f"{name}: {path}"
    if not path.exists():
        raise ValueError(f"{field}: no such file; download MSN's ViT-S/16 weights from {MSN_WEIGHTS_URL}")
    raw = load_inert(path, field, "torch file")
    state = raw.get("target_encoder", raw.get("model", raw)) if isinstance(raw, dict) else None
    if not isinstance(state, dict):
        raise ValueError(
            f"{field}: expected a state dict, MSN's checkpoint with 'target_encoder' or PC²'s with 'model'"
        )
    state = {k.removeprefix("module."): v for k, v in checked_state_dict(state, field).items()}
    if any(k.startswith(_PC2_PREFIX) for k in state):
        state = {k.removeprefix(_PC2_PREFIX): v for k, v in state.items() if k.startswith(_PC2_PREFIX)}
    state = {k: v for k, v in state.items() if not k.startswith("fc.")}
    expected = {k: v.shape for k, v in ViTS16().state_dict().items()}
    missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
    if missing or unexpected:
        raise ValueError(
            f"{field}: not MSN's ViT-S/16 key layout (missing {missing[:3]}{'…' if len(missing) > 3 else ''}, "
            f"unexpected {unexpected[:3]}{'…' if len(unexpected) > 3 else ''})"
        )
    wrong = [k for k, shape in expected.items() if state[k].shape != shape]
    if wrong:
        raise ValueError(
            f"{field}: {wrong[0]} has shape {tuple(state[wrong[0]].shape)}, ViT-S/16 needs {tuple(expected[wrong[0]])}"
        )
    return state


class _Tokens(NamedTuple):
    tokens: Tensor  # (384, S/16, S/16)

    def nbytes(self) -> int:
        return self.tokens.numel() * self.tokens.element_size()


class FrozenViT(nn.Module):
    """PC²'s frozen ViT-S/16 feature map: ``(B, 3, S, S)`` RGB → ``(B, 384, S, S)``.

    The backbone is held outside the module's parameters and state dict: no optimiser, EMA or
    checkpoint sees its 22 M weights, ``.to()`` still moves it, and it never leaves eval mode.
    A checkpoint stores :attr:`record` (the weights' SHA-256) instead.

    Frozen features depend only on the image, so the patch tokens of each image are cached by its
    bytes (least recently used out beyond ``cache_bytes``; ~0.3 MB per 224² image): held-out views
    are evaluated again at every evaluation, and captured data sets show each input view many times.

    Args:
        weights: local weights file (:func:`load_msn_state_dict`).
        cache_bytes: budget of the token cache; 0 disables it.
        field: the config field that named ``weights``, for messages.
    """

    def __init__(self, weights: str | Path, cache_bytes: int = 256 * 2**20, field: str = "model.encoder_weights"):
        super().__init__()
        state = load_msn_state_dict(weights, field)
        backbone = ViTS16()
        backbone.load_state_dict(state)
        self._backbone = [backbone.requires_grad_(False).eval()]  # a list: not a registered submodule
        self.out_channels = VIT_S16_CHANNELS
        digest = file_sha256(input_path(weights), "model.encoder_weights")
        self.record = {"encoder": "vit_s16", "weights_sha256": digest}
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.cache_bytes = cache_bytes
        self._cache: ByteLRU[_Tokens] = ByteLRU(cache_bytes)

    @property
    def backbone(self) -> ViTS16:
        return self._backbone[0]

    def _apply(self, fn, recurse: bool = True):
        super()._apply(fn, recurse)
        self.backbone._apply(fn, recurse)
        self._cache.clear()
        return self

    def _run(self, image: Tensor) -> Tensor:
        return self.backbone((image - self.mean) / self.std)

    def _tokens(self, image: Tensor) -> Tensor:
        if self.cache_bytes == 0:
            return self._run(image)
        keys = [hashlib.blake2b(img.detach().cpu().numpy().tobytes(), digest_size=16).digest() for img in image]
        todo = [i for i, k in enumerate(keys) if k not in self._cache]
        fresh = dict(zip((keys[i] for i in todo), self._run(image[todo]))) if todo else {}

        def make(i: int) -> _Tokens:
            return _Tokens(fresh[keys[i]] if keys[i] in fresh else self._run(image[i : i + 1])[0])

        return torch.stack([self._cache.get(k, lambda i=i: make(i)).tokens for i, k in enumerate(keys)])

    @torch.no_grad()
    def forward(self, image: Tensor, mask: Tensor, prior_2d: Tensor) -> Tensor:
        """Same signature as :meth:`ImageEncoder.forward`; only ``image`` (RGB in [0, 1]) is used."""
        return upsample_features(self.coarse(image, mask, prior_2d), image.shape[-1])

    @torch.no_grad()
    def coarse(self, image: Tensor, mask: Tensor, prior_2d: Tensor) -> Tensor:
        """:meth:`forward` before its bilinear upsampling: the ``(B, 384, S/16, S/16)`` patch-token grid."""
        s = image.shape[-1]
        if image.ndim != 4 or image.shape[1] != 3 or s % _PATCH or image.shape[-2] != s:
            raise ValueError(f"vit_s16 needs (B, 3, S, S) images with S a multiple of 16, got {tuple(image.shape)}")
        return self._tokens(image)


def upsample_features(coarse: Tensor, size: int) -> Tensor:
    """An encoder's ``coarse`` features ``(B, F, s, s)`` → ``(B, F, size, size)``: bilinear, ``align_corners=False``
    (PC²'s ``feature_model.py``). :func:`cdm.model.conditioning.features_at_pixels` samples the same
    values at chosen pixels only."""
    return F.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=False)


def build_encoder(cfg: ModelConfig, prior_2d_channels: int) -> ImageEncoder | FrozenViT:
    """The encoder ``model.encoder`` names (``vit_s16`` reads ``model.encoder_weights``, else ``model.init_from``)."""
    if cfg.encoder == "vit_s16" and cfg.encoder_weights is None:
        return FrozenViT(cfg.init_from, field="model.init_from")
    if cfg.encoder == "vit_s16":
        return FrozenViT(cfg.encoder_weights)
    return ImageEncoder(prior_2d_channels, cfg.feature_dim)


def check_encoder_record(saved: dict | None, current: dict) -> None:
    """Refuse a checkpoint whose encoder (or frozen weights, by SHA-256) differs from this network's.

    ``saved`` is the checkpoint's ``"encoder"`` entry; checkpoints written before it existed hold
    the CNN (``None`` reads as ``{"encoder": "cnn"}``).
    """
    saved = saved or {"encoder": "cnn"}
    if saved.get("encoder") != current.get("encoder"):
        raise ValueError(
            f"model.encoder: the checkpoint was trained with {saved.get('encoder')!r}, this network uses "
            f"{current.get('encoder')!r}; load it with model.encoder={saved.get('encoder')}"
        )
    if saved.get("weights_sha256") != current.get("weights_sha256"):
        raise ValueError(
            f"model.encoder_weights: the checkpoint's frozen encoder had weights sha256 {saved.get('weights_sha256')}, "
            f"this file has {current.get('weights_sha256')}; pass the weights it was trained with"
        )
