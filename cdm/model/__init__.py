"""CDM model: image encoder, projection conditioning, voxel branch, the two denoisers (PC²'s PVCNN2 and
our point-voxel network), PC²'s point operations and reference weights, network."""

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
from cdm.model.pvcnn2 import PVCNN2Denoiser, pc2_timestep_embedding
from cdm.model.reference_weights import (
    denoiser_from_reference,
    load_reference_checkpoint,
    load_reference_weights,
    reference_in_channels,
    reference_state_dict,
)
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
    "PVCNN2Denoiser",
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
    "denoiser_from_reference",
    "global_embedding",
    "image_tokens",
    "load_reference_checkpoint",
    "load_reference_weights",
    "mask_distance_transform",
    "normalize_coords",
    "pc2_timestep_embedding",
    "project_conditioning",
    "reference_in_channels",
    "reference_state_dict",
    "resolve_voxel_backend",
    "timestep_embedding",
]
