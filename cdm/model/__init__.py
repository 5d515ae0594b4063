"""CDM model: image encoder, projection conditioning, voxel branch, point-voxel denoiser, network."""

from cdm.model.conditioning import (
    conditioning_channels,
    conditioning_map,
    mask_distance_transform,
    project_conditioning,
)
from cdm.model.encoder import FrozenViT, ImageEncoder, ViTS16, build_encoder, check_encoder_record
from cdm.model.global_features import PointCrossAttention, global_embedding, image_tokens
from cdm.model.network import CDMNetwork, ImageContext
from cdm.model.pvcnn import PointVoxelBlock, PVCNNDenoiser, timestep_embedding
from cdm.model.voxels import (
    DenseGrid,
    SparseGrid,
    VoxelBranch,
    VoxelGrid,
    build_grid,
    normalize_coords,
    resolve_voxel_backend,
)

__all__ = [
    "CDMNetwork",
    "DenseGrid",
    "FrozenViT",
    "ImageContext",
    "ImageEncoder",
    "PVCNNDenoiser",
    "PointCrossAttention",
    "PointVoxelBlock",
    "SparseGrid",
    "VoxelBranch",
    "ViTS16",
    "VoxelGrid",
    "build_encoder",
    "check_encoder_record",
    "build_grid",
    "conditioning_channels",
    "conditioning_map",
    "global_embedding",
    "image_tokens",
    "mask_distance_transform",
    "normalize_coords",
    "project_conditioning",
    "resolve_voxel_backend",
    "timestep_embedding",
]
