"""The CDM network: image encoder → projection conditioning → point-voxel denoiser (PC² architecture).

Usage: ``context = net.encode(batch)`` once per image (encoder, conditioning map, global features),
then ``net(x_t, t, context, batch.camera)`` at every diffusion step — it rasterizes ``x_t`` from the
input camera, lifts the conditioning map onto the visible points and denoises.

The denoiser is ``model.denoiser``: PC²'s PVCNN2 (:mod:`cdm.model.pvcnn2`) or our point-voxel network
(:mod:`cdm.model.pvcnn`). With ``pvcnn2`` the conditioning channels come in PC²'s order, so that the
first-layer weights of a PC² checkpoint read the channels they were trained on
(``experiments/model/projection_model.py``: xyz, RGB normalised to [−1, 1], image features, mask,
distance transform, then global features); the 2D prior maps follow the image features (the paper's
Eq. 8, F_I ⊕ F_I*).
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from typing import NamedTuple

import torch
import torch.nn as nn
from torch import Tensor

from cdm.cameras import Cameras
from cdm.config import ModelConfig
from cdm.data.sample import Batch
from cdm.model.conditioning import conditioning_channels, conditioning_map, project_conditioning, project_views
from cdm.model.embeddings import load_embeddings
from cdm.model.encoder import build_encoder, upsample_features
from cdm.model.global_features import TOKEN_GRID, global_embedding, image_tokens
from cdm.model.pvcnn import PVCNNDenoiser
from cdm.model.pvcnn2 import PVCNN2Denoiser
from cdm.model.reference_weights import load_reference_checkpoint, load_reference_weights
from cdm.model.voxels import VoxelBackend, resolve_voxel_backend
from cdm.paths import input_path

__all__ = ["CDMNetwork", "ImageContext"]


class ImageContext(NamedTuple):
    """Everything the denoiser needs from the input image; computed once, reused by every step.

    Attributes:
        pixel: ``(B, C, S, S)`` conditioning map ``[features, 2D prior, RGB, mask, distance]``; with the
            ``pvcnn2`` denoiser in PC²'s order ``[2·RGB − 1, features, 2D prior, mask, distance]``. Without
            the feature channels when ``features`` holds them.
        embedding: ``(B, F)`` global embedding (``global_feature == "concat"``), else ``None``; ``(B, E)``
            from ``model.global_embeddings`` with ``global_source == "embeddings"``.
        tokens: ``(B, 64, F)`` image tokens (``global_feature == "cross_attention"``), else ``None``;
            ``(B, T, E)`` from the embeddings file.
    """

    pixel: Tensor
    embedding: Tensor | None
    tokens: Tensor | None
    views: Tensor | None = None
    """``(B, K, C, S, S)`` conditioning maps of the extra condition views (training with
    ``data.condition_views``), else ``None``."""
    view_cameras: Cameras | None = None
    """Their cameras, batch ``(B, K)``."""
    view_valid: Tensor | None = None
    """``(B, K)`` bool, the views each sample uses."""
    features: Tensor | None = None
    """``(B, F, s, s)`` the encoder's features before their bilinear upsampling to ``S``
    (``encoder.coarse``), when ``pixel`` lacks the feature channels: each point then samples them at
    its pixel (:func:`~cdm.model.conditioning.features_at_pixels`, the same values). ``None`` with
    condition views, whose maps hold every channel."""


class CDMNetwork(nn.Module):
    """Conditional denoiser ``(x_t, t, image) → (B, N, 3)``.

    Args:
        cfg: the model config group.
        prior_2d_channels: ``C2`` of ``batch.prior_2d`` (0 when ``priors.prior_2d`` is ``none``).
        device: where the model will run; only resolves ``voxel_backend="auto"`` (``None``: CUDA if
            available). Move the module yourself.
        encoder: replaces the one ``cfg.encoder`` names (:func:`~cdm.model.encoder.build_encoder`);
            its ``out_channels`` must equal ``cfg.feature_dim``.
        autocast: the dtype the image encoder and the denoiser compute in under torch autocast
            (``train.precision``, :data:`cdm.runtime.AUTOCAST_DTYPES`); None: float32. Their outputs
            are returned as float32; the projection of x_t onto the image stays float32.

    Attributes:
        voxel_backend: the resolved back-end, ``dense`` or ``sparse``. Record it with a checkpoint and
            rebuild with ``config.replace(**{"model.voxel_backend": ...})``: the two compute different
            functions with the same parameters. The ``pvcnn2`` denoiser ignores it (dense, as PC²).
    """

    def __init__(
        self,
        cfg: ModelConfig,
        prior_2d_channels: int,
        *,
        device: torch.device | str | None = None,
        encoder: nn.Module | None = None,
        autocast: torch.dtype | None = None,
    ):
        super().__init__()
        self.voxel_backend: VoxelBackend = resolve_voxel_backend(cfg.voxel_backend, device)
        self.autocast = autocast
        self.prior_2d_channels = prior_2d_channels
        self.raster_radius = cfg.raster_radius
        self.global_feature = cfg.global_feature
        self.encoder = encoder if encoder is not None else build_encoder(cfg, prior_2d_channels)
        if self.encoder.out_channels != cfg.feature_dim:
            raise ValueError(
                f"encoder gives {self.encoder.out_channels} channels but model.feature_dim is {cfg.feature_dim}"
            )
        self.mask_channels = cfg.mask_channels
        cond = conditioning_channels(cfg.feature_dim, prior_2d_channels, cfg.mask_channels)
        self.embeddings = load_embeddings(cfg.global_embeddings) if cfg.global_source == "embeddings" else None
        global_dim = cfg.feature_dim if self.embeddings is None else self.embeddings.dim
        in_channels = cond + (global_dim if cfg.global_feature == "concat" else 0)
        self.feature_dim = cfg.feature_dim
        self.pc2_order = cfg.denoiser == "pvcnn2"
        tokens = {"token_channels": global_dim if cfg.global_feature == "cross_attention" else None,
                  "num_tokens": TOKEN_GRID**2 if self.embeddings is None else self.embeddings.num_tokens}
        self.denoiser: nn.Module
        if self.pc2_order:
            self.denoiser = PVCNN2Denoiser(
                in_channels,
                cfg.width_multiplier,
                cfg.voxel_resolution_multiplier,
                embed_dim=cfg.time_embed_dim,
                **tokens,
            )
            if cfg.init_from is not None:
                path = input_path(cfg.init_from)
                try:
                    load_reference_weights(self.denoiser, load_reference_checkpoint(path, "pc2"))
                except ValueError as exc:
                    raise ValueError(f"model.init_from: {path}: {str(exc).removeprefix(f'{path} ')}") from None
            return
        self.denoiser = PVCNNDenoiser(
            in_channels=in_channels,
            widths=cfg.widths,
            resolutions=cfg.voxel_resolutions,
            time_embed_dim=cfg.time_embed_dim,
            voxel_backend=self.voxel_backend,
            devoxelize=cfg.devoxelize,
            **tokens,
        )

    def encode(self, batch: Batch) -> ImageContext:
        """Per-image work: encoder features, conditioning map and global features."""
        if batch.prior_2d.shape[1] != self.prior_2d_channels:
            raise ValueError(
                f"batch.prior_2d has {batch.prior_2d.shape[1]} channels, the network expects "
                f"{self.prior_2d_channels}; build it with the data's priors.prior_2d"
            )
        coarse = self._encode(batch.image, batch.mask, batch.prior_2d)
        size = batch.image.shape[-1]
        c = batch.conditions
        concat, attend = self.global_feature == "concat", self.global_feature == "cross_attention"
        pooled = upsample_features(coarse, size) if self.embeddings is None and (concat or attend) else None
        # A single view keeps its features coarse: a step samples them at N points, not S² pixels.
        features = None if c is None else upsample_features(coarse, size)
        pixel = self._arrange(conditioning_map(features, batch.prior_2d, batch.image, batch.mask, self.mask_channels),
                              with_features=features is not None)
        if self.embeddings is not None:
            given = self.embeddings.batch(batch.object_id).to(coarse)  # (B, T, E)
            context = ImageContext(pixel, given.mean(dim=1) if concat else None, given if attend else None)
        else:
            context = ImageContext(
                pixel, global_embedding(pooled) if concat else None, image_tokens(pooled) if attend else None
            )
        if c is None:
            return context._replace(features=coarse)
        image, mask, prior = (t.flatten(0, 1) for t in (c.image, c.mask, c.prior_2d))
        views = self._arrange(conditioning_map(upsample_features(self._encode(image, mask, prior), size), prior, image,
                                               mask, self.mask_channels))
        views = views.unflatten(0, c.valid.shape)
        return context._replace(views=views, view_cameras=c.camera, view_valid=c.valid)

    def _mixed_precision(self, device: torch.device) -> AbstractContextManager:
        return nullcontext() if self.autocast is None else torch.autocast(device.type, dtype=self.autocast)

    def _encode(self, image: Tensor, mask: Tensor, prior_2d: Tensor) -> Tensor:
        """The encoder's coarse features (``encoder.coarse``), float32."""
        with self._mixed_precision(image.device):
            return self.encoder.coarse(image, mask, prior_2d).float()

    @property
    def _feature_slot(self) -> int:
        """The channel of the conditioning at which the image features start: after RGB in PC²'s order."""
        return 3 if self.pc2_order else 0

    def _arrange(self, maps: Tensor, with_features: bool = True) -> Tensor:
        """``(B, C, S, S)`` conditioning maps ``[features, 2D prior, RGB, rest]`` → PC²'s order for ``pvcnn2``:
        ``[2·RGB − 1, features, 2D prior, rest]`` (``rest``: mask and distance transform, when projected).
        Maps ``with_features=False`` lack the features, which :func:`project_conditioning` inserts at
        :attr:`_feature_slot`.

        Done on the maps, before projection, so that hidden points get zeros in every channel as in PC².
        """
        if not self.pc2_order:
            return maps
        f = self.feature_dim if with_features else 0
        prior, rgb = f + self.prior_2d_channels, f + self.prior_2d_channels + 3
        return torch.cat([maps[:, prior:rgb] * 2.0 - 1.0, maps[:, :prior], maps[:, rgb:]], dim=1)

    def forward(self, x_t: Tensor, t: Tensor, context: ImageContext, camera: Cameras) -> Tensor:
        """One denoiser evaluation.

        Args:
            x_t: ``(B, N, 3)`` noisy points, world frame of the normalised object.
            t: ``(B,)`` long timesteps in ``[0, T)``.
            context: from :meth:`encode` for the same ``B`` images.
            camera: input cameras, batch ``(B,)``.
        Returns:
            ``(B, N, 3)`` raw network output.
        """
        if x_t.ndim != 3 or x_t.shape[-1] != 3:
            raise ValueError(f"x_t must be (B, N, 3), got shape {tuple(x_t.shape)}")
        if t.shape != x_t.shape[:1] or context.pixel.shape[0] != x_t.shape[0]:
            raise ValueError(
                f"t {tuple(t.shape)} and context (batch {context.pixel.shape[0]}) must match x_t's batch {x_t.shape[0]}"
            )
        if context.views is None:
            cond = project_conditioning(context.pixel, x_t, camera, self.raster_radius, context.features,
                                        self._feature_slot)
        else:
            fields = ("R", "T", "focal", "principal")
            cameras = Cameras(
                *(torch.cat([getattr(camera, f)[:, None], getattr(context.view_cameras, f)], 1) for f in fields)
            )
            valid = torch.cat([context.view_valid.new_ones(x_t.shape[0], 1), context.view_valid], dim=1)
            maps = torch.cat([context.pixel[:, None], context.views], dim=1)
            cond = project_views(maps, x_t, cameras, valid, self.raster_radius)
        if context.embedding is not None:
            cond = torch.cat([cond, context.embedding[:, None, :].expand(-1, x_t.shape[1], -1)], dim=-1)
        with self._mixed_precision(x_t.device):
            return self.denoiser(x_t, cond, t, context.tokens).float()
