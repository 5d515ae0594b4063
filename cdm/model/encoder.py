"""Image encoders: per-pixel feature maps that projection conditioning lifts onto points.

- :class:`ImageEncoder` — a small trainable CNN over RGB, mask and the 2D-prior channels (Eq. 7),
  our default. PC² instead uses a frozen ViT-S/16 (384 channels) upsampled to 224²; a frozen network
  costs no backward pass and its features can be cached per image.
- :class:`FrozenEncoder` — wraps any ``nn.Module`` whose weights come from a **local** file (a state
  dict saved with ``torch.save``), frozen. Nothing is downloaded: fetch and convert pretrained
  weights yourself, then pass the path.

Both map ``image (B, 3, S, S)``, ``mask (B, 1, S, S)``, ``prior_2d (B, C2, S, S)`` to
``(B, out_channels, S, S)`` in the pixel layout of :mod:`cdm.cameras`, and expose ``out_channels``.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from cdm.model.voxels import norm_groups

__all__ = ["FrozenEncoder", "ImageEncoder"]


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
        if prior_2d.shape[1] != self.prior_2d_channels:
            raise ValueError(
                f"prior_2d has {prior_2d.shape[1]} channels but the encoder was built for {self.prior_2d_channels}"
            )
        size = image.shape[-2:]
        half = self.down1(torch.cat([image, mask, prior_2d], dim=1))
        quarter = self.mid(self.down2(half))
        up = F.interpolate(quarter, size=half.shape[-2:], mode="bilinear", align_corners=False)
        features = self.out(torch.cat([up, half], dim=1))
        return F.interpolate(features, size=size, mode="bilinear", align_corners=False)


class FrozenEncoder(nn.Module):
    """A frozen feature network loaded from a local state-dict file (no downloads).

    ``backbone(image)`` must take RGB ``(B, 3, S, S)`` in [0, 1] (wrap any normalisation the weights
    expect into the module) and return ``(B, out_channels, h, w)`` at any ``h, w``; the result is
    upsampled bilinearly to ``S × S`` (as PC² does with ViT patch features). Mask and 2D prior are
    not seen by the backbone; projection conditioning still appends them per point.

    The backbone stays in eval mode and without gradients whatever ``.train()`` is called with.

    Args:
        backbone: the architecture, with freshly initialised weights.
        weights: path of a ``torch.save(state_dict)`` file, loaded with ``weights_only=True``.
        out_channels: channels the backbone returns (must equal ``model.feature_dim``).
    """

    def __init__(self, backbone: nn.Module, weights: str | Path, out_channels: int):
        super().__init__()
        path = Path(weights)
        if not path.is_file():
            raise ValueError(f"encoder weights {path}: no such file; save a state dict there with torch.save")
        backbone.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        backbone.requires_grad_(False)
        self.backbone = backbone.eval()
        self.out_channels = out_channels

    def train(self, mode: bool = True) -> FrozenEncoder:
        super().train(mode)
        self.backbone.eval()
        return self

    @torch.no_grad()
    def forward(self, image: Tensor, mask: Tensor, prior_2d: Tensor) -> Tensor:
        """Same signature as :meth:`ImageEncoder.forward`; only ``image`` is used."""
        features = self.backbone(image)
        if features.ndim != 4 or features.shape[1] != self.out_channels:
            raise ValueError(
                f"frozen backbone returned shape {tuple(features.shape)}, expected (B, {self.out_channels}, h, w)"
            )
        return F.interpolate(features, size=image.shape[-2:], mode="bilinear", align_corners=False)
