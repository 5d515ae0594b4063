"""PC²'s PVCNN2 (``cdm.model.pvcnn2``): PC²'s parameters exactly, forward/backward, learning, reference weights."""

from __future__ import annotations

import pytest
import torch

from cdm.model import CDMNetwork, conditioning_channels, mask_distance_transform
from cdm.model.encoder import upsample_features
from cdm.model.pvcnn2 import PVCNN2Denoiser, SelfAttention, pc2_timestep_embedding
from cdm.model.reference_weights import (
    denoiser_from_reference,
    load_reference_checkpoint,
    load_reference_weights,
    reference_in_channels,
    reference_state_dict,
)
from cdm.prior_model import PriorNetwork
from tests.test_model import tiny_batch

# Every parameter (name, shape) of PC²'s PVCNN2 at its default 392 input channels (xyz + RGB 3 +
# ViT-S/16 384 + mask 1 + distance transform 1), in ``named_parameters()`` order. Source: PC²'s own
# code, lukemelas/projection-conditioned-point-cloud-diffusion at commit
# 64fd55a0d00b52735cf02e11c5112374c7104ece, ``experiments/model/pvcnn/pvcnn.py`` ``PVCNN2(num_classes=3,
# embed_dim=64, extra_feature_channels=389, dropout=0.1)``, built on CPU with its CUDA backend
# (``modules/functional/backend.py``) stubbed out: the compiled ops hold no parameters.
PC2_PARAMETERS_392 = """
sa_layers.0.0.voxel_layers.0.weight 32x392x3x3x3
sa_layers.0.0.voxel_layers.0.bias 32
sa_layers.0.0.voxel_layers.1.weight 32
sa_layers.0.0.voxel_layers.1.bias 32
sa_layers.0.0.voxel_layers.4.weight 32x32x3x3x3
sa_layers.0.0.voxel_layers.4.bias 32
sa_layers.0.0.voxel_layers.5.weight 32
sa_layers.0.0.voxel_layers.5.bias 32
sa_layers.0.0.voxel_layers.7.fc.0.weight 4x32
sa_layers.0.0.voxel_layers.7.fc.2.weight 32x4
sa_layers.0.0.point_features.layers.0.weight 32x392x1
sa_layers.0.0.point_features.layers.0.bias 32
sa_layers.0.0.point_features.layers.1.weight 32
sa_layers.0.0.point_features.layers.1.bias 32
sa_layers.0.1.voxel_layers.0.weight 32x32x3x3x3
sa_layers.0.1.voxel_layers.0.bias 32
sa_layers.0.1.voxel_layers.1.weight 32
sa_layers.0.1.voxel_layers.1.bias 32
sa_layers.0.1.voxel_layers.4.weight 32x32x3x3x3
sa_layers.0.1.voxel_layers.4.bias 32
sa_layers.0.1.voxel_layers.5.weight 32
sa_layers.0.1.voxel_layers.5.bias 32
sa_layers.0.1.voxel_layers.7.fc.0.weight 4x32
sa_layers.0.1.voxel_layers.7.fc.2.weight 32x4
sa_layers.0.1.point_features.layers.0.weight 32x32x1
sa_layers.0.1.point_features.layers.0.bias 32
sa_layers.0.1.point_features.layers.1.weight 32
sa_layers.0.1.point_features.layers.1.bias 32
sa_layers.0.2.mlps.0.layers.0.weight 32x35x1x1
sa_layers.0.2.mlps.0.layers.0.bias 32
sa_layers.0.2.mlps.0.layers.1.weight 32
sa_layers.0.2.mlps.0.layers.1.bias 32
sa_layers.0.2.mlps.0.layers.3.weight 64x32x1x1
sa_layers.0.2.mlps.0.layers.3.bias 64
sa_layers.0.2.mlps.0.layers.4.weight 64
sa_layers.0.2.mlps.0.layers.4.bias 64
sa_layers.1.0.voxel_layers.0.weight 64x128x3x3x3
sa_layers.1.0.voxel_layers.0.bias 64
sa_layers.1.0.voxel_layers.1.weight 64
sa_layers.1.0.voxel_layers.1.bias 64
sa_layers.1.0.voxel_layers.4.weight 64x64x3x3x3
sa_layers.1.0.voxel_layers.4.bias 64
sa_layers.1.0.voxel_layers.5.weight 64
sa_layers.1.0.voxel_layers.5.bias 64
sa_layers.1.0.voxel_layers.6.q.weight 64x64x1x1x1
sa_layers.1.0.voxel_layers.6.q.bias 64
sa_layers.1.0.voxel_layers.6.k.weight 64x64x1x1x1
sa_layers.1.0.voxel_layers.6.k.bias 64
sa_layers.1.0.voxel_layers.6.v.weight 64x64x1x1x1
sa_layers.1.0.voxel_layers.6.v.bias 64
sa_layers.1.0.voxel_layers.6.out.weight 64x64x1x1x1
sa_layers.1.0.voxel_layers.6.out.bias 64
sa_layers.1.0.voxel_layers.6.norm.weight 64
sa_layers.1.0.voxel_layers.6.norm.bias 64
sa_layers.1.0.voxel_layers.7.fc.0.weight 8x64
sa_layers.1.0.voxel_layers.7.fc.2.weight 64x8
sa_layers.1.0.point_features.layers.0.weight 64x128x1
sa_layers.1.0.point_features.layers.0.bias 64
sa_layers.1.0.point_features.layers.1.weight 64
sa_layers.1.0.point_features.layers.1.bias 64
sa_layers.1.1.mlps.0.layers.0.weight 64x67x1x1
sa_layers.1.1.mlps.0.layers.0.bias 64
sa_layers.1.1.mlps.0.layers.1.weight 64
sa_layers.1.1.mlps.0.layers.1.bias 64
sa_layers.1.1.mlps.0.layers.3.weight 128x64x1x1
sa_layers.1.1.mlps.0.layers.3.bias 128
sa_layers.1.1.mlps.0.layers.4.weight 128
sa_layers.1.1.mlps.0.layers.4.bias 128
sa_layers.2.0.voxel_layers.0.weight 128x192x3x3x3
sa_layers.2.0.voxel_layers.0.bias 128
sa_layers.2.0.voxel_layers.1.weight 128
sa_layers.2.0.voxel_layers.1.bias 128
sa_layers.2.0.voxel_layers.4.weight 128x128x3x3x3
sa_layers.2.0.voxel_layers.4.bias 128
sa_layers.2.0.voxel_layers.5.weight 128
sa_layers.2.0.voxel_layers.5.bias 128
sa_layers.2.0.voxel_layers.7.fc.0.weight 16x128
sa_layers.2.0.voxel_layers.7.fc.2.weight 128x16
sa_layers.2.0.point_features.layers.0.weight 128x192x1
sa_layers.2.0.point_features.layers.0.bias 128
sa_layers.2.0.point_features.layers.1.weight 128
sa_layers.2.0.point_features.layers.1.bias 128
sa_layers.2.1.mlps.0.layers.0.weight 128x131x1x1
sa_layers.2.1.mlps.0.layers.0.bias 128
sa_layers.2.1.mlps.0.layers.1.weight 128
sa_layers.2.1.mlps.0.layers.1.bias 128
sa_layers.2.1.mlps.0.layers.3.weight 256x128x1x1
sa_layers.2.1.mlps.0.layers.3.bias 256
sa_layers.2.1.mlps.0.layers.4.weight 256
sa_layers.2.1.mlps.0.layers.4.bias 256
sa_layers.3.mlps.0.layers.0.weight 256x323x1x1
sa_layers.3.mlps.0.layers.0.bias 256
sa_layers.3.mlps.0.layers.1.weight 256
sa_layers.3.mlps.0.layers.1.bias 256
sa_layers.3.mlps.0.layers.3.weight 256x256x1x1
sa_layers.3.mlps.0.layers.3.bias 256
sa_layers.3.mlps.0.layers.4.weight 256
sa_layers.3.mlps.0.layers.4.bias 256
sa_layers.3.mlps.0.layers.6.weight 512x256x1x1
sa_layers.3.mlps.0.layers.6.bias 512
sa_layers.3.mlps.0.layers.7.weight 512
sa_layers.3.mlps.0.layers.7.bias 512
global_att.q.weight 512x512x1
global_att.q.bias 512
global_att.k.weight 512x512x1
global_att.k.bias 512
global_att.v.weight 512x512x1
global_att.v.bias 512
global_att.out.weight 512x512x1
global_att.out.bias 512
global_att.norm.weight 512
global_att.norm.bias 512
fp_layers.0.0.mlp.layers.0.weight 256x832x1
fp_layers.0.0.mlp.layers.0.bias 256
fp_layers.0.0.mlp.layers.1.weight 256
fp_layers.0.0.mlp.layers.1.bias 256
fp_layers.0.0.mlp.layers.3.weight 256x256x1
fp_layers.0.0.mlp.layers.3.bias 256
fp_layers.0.0.mlp.layers.4.weight 256
fp_layers.0.0.mlp.layers.4.bias 256
fp_layers.0.1.voxel_layers.0.weight 256x256x3x3x3
fp_layers.0.1.voxel_layers.0.bias 256
fp_layers.0.1.voxel_layers.1.weight 256
fp_layers.0.1.voxel_layers.1.bias 256
fp_layers.0.1.voxel_layers.4.weight 256x256x3x3x3
fp_layers.0.1.voxel_layers.4.bias 256
fp_layers.0.1.voxel_layers.5.weight 256
fp_layers.0.1.voxel_layers.5.bias 256
fp_layers.0.1.voxel_layers.7.fc.0.weight 32x256
fp_layers.0.1.voxel_layers.7.fc.2.weight 256x32
fp_layers.0.1.point_features.layers.0.weight 256x256x1
fp_layers.0.1.point_features.layers.0.bias 256
fp_layers.0.1.point_features.layers.1.weight 256
fp_layers.0.1.point_features.layers.1.bias 256
fp_layers.0.2.voxel_layers.0.weight 256x256x3x3x3
fp_layers.0.2.voxel_layers.0.bias 256
fp_layers.0.2.voxel_layers.1.weight 256
fp_layers.0.2.voxel_layers.1.bias 256
fp_layers.0.2.voxel_layers.4.weight 256x256x3x3x3
fp_layers.0.2.voxel_layers.4.bias 256
fp_layers.0.2.voxel_layers.5.weight 256
fp_layers.0.2.voxel_layers.5.bias 256
fp_layers.0.2.voxel_layers.7.fc.0.weight 32x256
fp_layers.0.2.voxel_layers.7.fc.2.weight 256x32
fp_layers.0.2.point_features.layers.0.weight 256x256x1
fp_layers.0.2.point_features.layers.0.bias 256
fp_layers.0.2.point_features.layers.1.weight 256
fp_layers.0.2.point_features.layers.1.bias 256
fp_layers.0.3.voxel_layers.0.weight 256x256x3x3x3
fp_layers.0.3.voxel_layers.0.bias 256
fp_layers.0.3.voxel_layers.1.weight 256
fp_layers.0.3.voxel_layers.1.bias 256
fp_layers.0.3.voxel_layers.4.weight 256x256x3x3x3
fp_layers.0.3.voxel_layers.4.bias 256
fp_layers.0.3.voxel_layers.5.weight 256
fp_layers.0.3.voxel_layers.5.bias 256
fp_layers.0.3.voxel_layers.7.fc.0.weight 32x256
fp_layers.0.3.voxel_layers.7.fc.2.weight 256x32
fp_layers.0.3.point_features.layers.0.weight 256x256x1
fp_layers.0.3.point_features.layers.0.bias 256
fp_layers.0.3.point_features.layers.1.weight 256
fp_layers.0.3.point_features.layers.1.bias 256
fp_layers.1.0.mlp.layers.0.weight 256x448x1
fp_layers.1.0.mlp.layers.0.bias 256
fp_layers.1.0.mlp.layers.1.weight 256
fp_layers.1.0.mlp.layers.1.bias 256
fp_layers.1.0.mlp.layers.3.weight 256x256x1
fp_layers.1.0.mlp.layers.3.bias 256
fp_layers.1.0.mlp.layers.4.weight 256
fp_layers.1.0.mlp.layers.4.bias 256
fp_layers.1.1.voxel_layers.0.weight 256x256x3x3x3
fp_layers.1.1.voxel_layers.0.bias 256
fp_layers.1.1.voxel_layers.1.weight 256
fp_layers.1.1.voxel_layers.1.bias 256
fp_layers.1.1.voxel_layers.4.weight 256x256x3x3x3
fp_layers.1.1.voxel_layers.4.bias 256
fp_layers.1.1.voxel_layers.5.weight 256
fp_layers.1.1.voxel_layers.5.bias 256
fp_layers.1.1.voxel_layers.7.fc.0.weight 32x256
fp_layers.1.1.voxel_layers.7.fc.2.weight 256x32
fp_layers.1.1.point_features.layers.0.weight 256x256x1
fp_layers.1.1.point_features.layers.0.bias 256
fp_layers.1.1.point_features.layers.1.weight 256
fp_layers.1.1.point_features.layers.1.bias 256
fp_layers.1.2.voxel_layers.0.weight 256x256x3x3x3
fp_layers.1.2.voxel_layers.0.bias 256
fp_layers.1.2.voxel_layers.1.weight 256
fp_layers.1.2.voxel_layers.1.bias 256
fp_layers.1.2.voxel_layers.4.weight 256x256x3x3x3
fp_layers.1.2.voxel_layers.4.bias 256
fp_layers.1.2.voxel_layers.5.weight 256
fp_layers.1.2.voxel_layers.5.bias 256
fp_layers.1.2.voxel_layers.7.fc.0.weight 32x256
fp_layers.1.2.voxel_layers.7.fc.2.weight 256x32
fp_layers.1.2.point_features.layers.0.weight 256x256x1
fp_layers.1.2.point_features.layers.0.bias 256
fp_layers.1.2.point_features.layers.1.weight 256
fp_layers.1.2.point_features.layers.1.bias 256
fp_layers.1.3.voxel_layers.0.weight 256x256x3x3x3
fp_layers.1.3.voxel_layers.0.bias 256
fp_layers.1.3.voxel_layers.1.weight 256
fp_layers.1.3.voxel_layers.1.bias 256
fp_layers.1.3.voxel_layers.4.weight 256x256x3x3x3
fp_layers.1.3.voxel_layers.4.bias 256
fp_layers.1.3.voxel_layers.5.weight 256
fp_layers.1.3.voxel_layers.5.bias 256
fp_layers.1.3.voxel_layers.7.fc.0.weight 32x256
fp_layers.1.3.voxel_layers.7.fc.2.weight 256x32
fp_layers.1.3.point_features.layers.0.weight 256x256x1
fp_layers.1.3.point_features.layers.0.bias 256
fp_layers.1.3.point_features.layers.1.weight 256
fp_layers.1.3.point_features.layers.1.bias 256
fp_layers.2.0.mlp.layers.0.weight 256x384x1
fp_layers.2.0.mlp.layers.0.bias 256
fp_layers.2.0.mlp.layers.1.weight 256
fp_layers.2.0.mlp.layers.1.bias 256
fp_layers.2.0.mlp.layers.3.weight 128x256x1
fp_layers.2.0.mlp.layers.3.bias 128
fp_layers.2.0.mlp.layers.4.weight 128
fp_layers.2.0.mlp.layers.4.bias 128
fp_layers.2.1.voxel_layers.0.weight 128x128x3x3x3
fp_layers.2.1.voxel_layers.0.bias 128
fp_layers.2.1.voxel_layers.1.weight 128
fp_layers.2.1.voxel_layers.1.bias 128
fp_layers.2.1.voxel_layers.4.weight 128x128x3x3x3
fp_layers.2.1.voxel_layers.4.bias 128
fp_layers.2.1.voxel_layers.5.weight 128
fp_layers.2.1.voxel_layers.5.bias 128
fp_layers.2.1.voxel_layers.7.fc.0.weight 16x128
fp_layers.2.1.voxel_layers.7.fc.2.weight 128x16
fp_layers.2.1.point_features.layers.0.weight 128x128x1
fp_layers.2.1.point_features.layers.0.bias 128
fp_layers.2.1.point_features.layers.1.weight 128
fp_layers.2.1.point_features.layers.1.bias 128
fp_layers.2.2.voxel_layers.0.weight 128x128x3x3x3
fp_layers.2.2.voxel_layers.0.bias 128
fp_layers.2.2.voxel_layers.1.weight 128
fp_layers.2.2.voxel_layers.1.bias 128
fp_layers.2.2.voxel_layers.4.weight 128x128x3x3x3
fp_layers.2.2.voxel_layers.4.bias 128
fp_layers.2.2.voxel_layers.5.weight 128
fp_layers.2.2.voxel_layers.5.bias 128
fp_layers.2.2.voxel_layers.7.fc.0.weight 16x128
fp_layers.2.2.voxel_layers.7.fc.2.weight 128x16
fp_layers.2.2.point_features.layers.0.weight 128x128x1
fp_layers.2.2.point_features.layers.0.bias 128
fp_layers.2.2.point_features.layers.1.weight 128
fp_layers.2.2.point_features.layers.1.bias 128
fp_layers.3.0.mlp.layers.0.weight 128x581x1
fp_layers.3.0.mlp.layers.0.bias 128
fp_layers.3.0.mlp.layers.1.weight 128
fp_layers.3.0.mlp.layers.1.bias 128
fp_layers.3.0.mlp.layers.3.weight 128x128x1
fp_layers.3.0.mlp.layers.3.bias 128
fp_layers.3.0.mlp.layers.4.weight 128
fp_layers.3.0.mlp.layers.4.bias 128
fp_layers.3.0.mlp.layers.6.weight 64x128x1
fp_layers.3.0.mlp.layers.6.bias 64
fp_layers.3.0.mlp.layers.7.weight 64
fp_layers.3.0.mlp.layers.7.bias 64
fp_layers.3.1.voxel_layers.0.weight 64x64x3x3x3
fp_layers.3.1.voxel_layers.0.bias 64
fp_layers.3.1.voxel_layers.1.weight 64
fp_layers.3.1.voxel_layers.1.bias 64
fp_layers.3.1.voxel_layers.4.weight 64x64x3x3x3
fp_layers.3.1.voxel_layers.4.bias 64
fp_layers.3.1.voxel_layers.5.weight 64
fp_layers.3.1.voxel_layers.5.bias 64
fp_layers.3.1.voxel_layers.7.fc.0.weight 8x64
fp_layers.3.1.voxel_layers.7.fc.2.weight 64x8
fp_layers.3.1.point_features.layers.0.weight 64x64x1
fp_layers.3.1.point_features.layers.0.bias 64
fp_layers.3.1.point_features.layers.1.weight 64
fp_layers.3.1.point_features.layers.1.bias 64
fp_layers.3.2.voxel_layers.0.weight 64x64x3x3x3
fp_layers.3.2.voxel_layers.0.bias 64
fp_layers.3.2.voxel_layers.1.weight 64
fp_layers.3.2.voxel_layers.1.bias 64
fp_layers.3.2.voxel_layers.4.weight 64x64x3x3x3
fp_layers.3.2.voxel_layers.4.bias 64
fp_layers.3.2.voxel_layers.5.weight 64
fp_layers.3.2.voxel_layers.5.bias 64
fp_layers.3.2.voxel_layers.7.fc.0.weight 8x64
fp_layers.3.2.voxel_layers.7.fc.2.weight 64x8
fp_layers.3.2.point_features.layers.0.weight 64x64x1
fp_layers.3.2.point_features.layers.0.bias 64
fp_layers.3.2.point_features.layers.1.weight 64
fp_layers.3.2.point_features.layers.1.bias 64
classifier.0.layers.0.weight 128x64x1
classifier.0.layers.0.bias 128
classifier.0.layers.1.weight 128
classifier.0.layers.1.bias 128
classifier.2.weight 3x128x1
classifier.2.bias 3
embedf.0.weight 64x64
embedf.0.bias 64
embedf.2.weight 64x64
embedf.2.bias 64
"""

# The shapes that depend on the input channels C = 3 + S (the same build with other S):
# SA1's voxel and point convolutions read C, FP4's first layer reads S + 128 + 64.
_INPUT_DEPENDENT = {
    "sa_layers.0.0.voxel_layers.0.weight": lambda c: (32, c, 3, 3, 3),
    "sa_layers.0.0.point_features.layers.0.weight": lambda c: (32, c, 1),
    "fp_layers.3.0.mlp.layers.0.weight": lambda c: (128, c - 3 + 128 + 64, 1),
}


def pc2_parameters(in_channels: int = 392) -> list[tuple[str, tuple[int, ...]]]:
    """PC²'s parameter list at ``in_channels`` inputs (xyz included)."""
    out = []
    for line in PC2_PARAMETERS_392.strip().splitlines():
        name, shape = line.split()
        dims = tuple(int(d) for d in shape.split("x"))
        out.append((name, _INPUT_DEPENDENT[name](in_channels) if name in _INPUT_DEPENDENT else dims))
    return out


def _count(params: list[tuple[str, tuple[int, ...]]]) -> int:
    total = 0
    for _, shape in params:
        n = 1
        for d in shape:
            n *= d
        total += n
    return total


def test_parameters_equal_pc2s_at_its_default_inputs():
    ours = [(n, tuple(p.shape)) for n, p in PVCNN2Denoiser(389).named_parameters()]
    assert ours == pc2_parameters(392)
    assert _count(ours) == 28_048_323


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (0, 27_649_987),  # xyz alone: PVD's unconditional prior (BDM)
        (387, 28_046_275),  # PC² on ShapeNet R2N2 as BDM runs it: use_mask, use_distance_transform off
        (388, 28_047_299),  # the same + the contour prior (CDM on ShapeNet)
        (390, 28_049_347),  # PC²'s inputs + a contour or depth prior map (the paper's Eq. 8, F_I ⊕ F_I*)
        (392, 28_051_395),  # + a 3-channel prior
    ],
)
def test_each_input_channel_adds_1024_parameters(extra: int, expected: int):
    model = PVCNN2Denoiser(extra)
    assert sum(p.numel() for p in model.parameters()) == expected == 28_048_323 + 1_024 * (extra - 389)
    assert [(n, tuple(p.shape)) for n, p in model.named_parameters()] == pc2_parameters(3 + extra)


def test_head_starts_near_zero_and_multipliers_scale_as_pc2s():
    model = PVCNN2Denoiser(4)
    head = model.classifier[-1]
    assert head.weight.abs().max() < 1e-5 and head.bias.abs().max() < 1e-5
    assert 0 < head.weight.std() < 2e-6
    # PC²'s int(multiplier × width) / int(multiplier × resolution), counted with its code: 1,822,707.
    small = PVCNN2Denoiser(5, width_multiplier=0.25, voxel_resolution_multiplier=0.5)
    assert sum(p.numel() for p in small.parameters()) == 1_822_707
    assert [m.resolution for m in small.modules() if hasattr(m, "resolution")] == [
        16,
        16,
        8,
        4,
        4,
        4,
        4,
        4,
        4,
        4,
        8,
        8,
        16,
        16,
    ]
    with pytest.raises(ValueError, match="model.width_multiplier=0.3"):
        PVCNN2Denoiser(4, width_multiplier=0.3)


def test_forward_backward_at_b2_n2048_full_width():
    torch.manual_seed(0)
    model = PVCNN2Denoiser(389)
    x_t, cond = torch.randn(2, 2048, 3), torch.randn(2, 2048, 389)
    out = model(x_t, cond, torch.tensor([5, 950]))
    assert out.shape == (2, 2048, 3) and torch.isfinite(out).all()
    assert 0 < out.abs().max() < 1e-3  # the N(0, 1e-6) head
    out.square().mean().backward()
    grads = {n: p.grad for n, p in model.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values())
    assert sum(int(g.abs().sum() > 0) for g in grads.values()) == len(grads)


def test_time_and_conditioning_change_the_output_and_shapes_are_checked():
    torch.manual_seed(1)
    model = PVCNN2Denoiser(2, width_multiplier=0.25, voxel_resolution_multiplier=0.25).eval()
    with torch.no_grad():
        model.classifier[-1].weight.normal_(0, 0.1)
    x_t, cond = torch.randn(1, 300, 3), torch.randn(1, 300, 2)
    with torch.no_grad():
        a = model(x_t, cond, torch.tensor([10]))
        b = model(x_t, cond, torch.tensor([900]))
        c = model(x_t, cond.flip(1), torch.tensor([10]))
        again = model(x_t, cond, torch.tensor([10]))
    assert torch.equal(a, again)
    assert (a - b).abs().max() > 1e-3 and (a - c).abs().max() > 1e-3
    with pytest.raises(ValueError, match=r"conditioning must be \(B, N, 2\)"):
        model(x_t, cond[..., :1], torch.tensor([10]))
    with pytest.raises(ValueError, match="pass tokens exactly when"):
        model(x_t, cond, torch.tensor([10]), tokens=torch.zeros(1, 4, 8))


def test_short_training_on_a_fixed_problem_lowers_the_loss():
    g = torch.Generator().manual_seed(2)
    model = PVCNN2Denoiser(2, width_multiplier=0.25, voxel_resolution_multiplier=0.25)
    x0 = torch.rand(2, 256, 3, generator=g) * 2 - 1
    eps = torch.randn(2, 256, 3, generator=g)
    t = torch.tensor([100, 400])
    x_t = 0.8 * x0 + 0.6 * eps
    cond = torch.randn(2, 256, 2, generator=g)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(20):
        loss = (model(x_t, cond, t) - eps).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[0] == pytest.approx(1.0, abs=0.3)  # the head starts at ≈ 0: loss ≈ E[ε²]
    assert losses[-1] < 0.6 * losses[0]  # measured: 1.00 → 0.48 in 20 steps
    assert all(b < a for a, b in zip(losses[2:], losses[3:]))  # and falling steadily after two steps


def _pc2_checkpoint(in_channels: int = 392, prefix: str = "point_cloud_model.model.") -> dict:
    """A PC²-shaped checkpoint: PVCNN2 under the diffusion model's names, other modules and entries beside it."""
    g = torch.Generator().manual_seed(3)
    model = {prefix + n: torch.randn(s, generator=g) for n, s in pc2_parameters(in_channels)}
    model["feature_model.model.cls_token"] = torch.zeros(1, 1, 384)
    return {"model": model, "optimizer": {"state": {}}, "step": 100_000, "model_ema": {}}


@pytest.mark.parametrize("prefix", ["point_cloud_model.model.", "module.point_cloud_model.model."])
def test_a_pc2_checkpoint_loads_key_for_key(prefix: str):
    ckpt = _pc2_checkpoint(prefix=prefix)
    state = reference_state_dict(ckpt, "pc2")
    assert reference_in_channels(state) == 389
    model = PVCNN2Denoiser(389)
    load_reference_weights(model, state)
    for name, p in model.named_parameters():
        assert torch.equal(p, ckpt["model"][prefix + name])


def test_a_pvd_checkpoint_loads_as_bdms_prior():
    g = torch.Generator().manual_seed(4)
    ckpt = {"epoch": 9, "model_state": {"model.module." + n: torch.randn(s, generator=g) for n, s in pc2_parameters(3)}}
    state = reference_state_dict(ckpt, "pvd")
    assert reference_in_channels(state) == 0
    model = PVCNN2Denoiser(0)
    load_reference_weights(model, state)
    assert torch.equal(
        model.fp_layers[3][0].mlp.layers[0].weight,
        ckpt["model_state"]["model.module.fp_layers.3.0.mlp.layers.0.weight"],
    )
    bdm = {"prior_model": {"model." + n: v for n, v in state.items()}}  # BDM's other container, no DataParallel
    assert reference_state_dict(bdm, "pvd").keys() == state.keys()
    out = model(torch.randn(1, 200, 3), torch.zeros(1, 200, 0), torch.tensor([3]))
    assert out.shape == (1, 200, 3)


def test_mismatches_are_refused_naming_the_first():
    state = reference_state_dict(_pc2_checkpoint(), "pc2")
    model = PVCNN2Denoiser(389)
    before = model.global_att.q.weight.clone()
    wrong = dict(state)
    wrong["fp_layers.1.0.mlp.layers.0.weight"] = torch.zeros(256, 447, 1)
    wrong["fp_layers.2.0.mlp.layers.0.weight"] = torch.zeros(1)
    with pytest.raises(
        ValueError, match=r"'fp_layers.1.0.mlp.layers.0.weight' has shape \(256, 447, 1\).*\(256, 448, 1\)"
    ):
        load_reference_weights(model, wrong)
    assert torch.equal(model.global_att.q.weight, before)  # nothing copied
    with pytest.raises(ValueError, match=r"'sa_layers.0.0.voxel_layers.0.weight' has shape \(32, 392, 3, 3, 3\)"):
        load_reference_weights(PVCNN2Denoiser(0), state)  # a PC² checkpoint is not a PVD prior
    missing = {k: v for k, v in state.items() if k != "global_att.norm.bias"}
    with pytest.raises(ValueError, match="lack 'global_att.norm.bias'"):
        load_reference_weights(model, missing)
    with pytest.raises(ValueError, match="hold 'extra.weight'"):
        load_reference_weights(model, {**state, "extra.weight": torch.zeros(1)})
    with pytest.raises(ValueError, match="no pvd PVCNN2 weights found"):
        reference_state_dict({"model_state": {"encoder.weight": torch.zeros(1)}}, "pvd")


class _Config:
    """A pickled object of a class outside OmegaConf's: creating it would run this module's code."""


def test_checkpoint_files_load_as_data_and_an_object_that_is_not_a_config_is_refused(tmp_path):
    path = tmp_path / "pc2.pth"
    torch.save(_pc2_checkpoint(), path)
    model = denoiser_from_reference(path, "pc2")
    assert model.in_channels == 389
    with_cfg = tmp_path / "with_cfg.pth"
    torch.save({**_pc2_checkpoint(), "cfg": _Config()}, with_cfg)  # PC²'s OmegaConf cfg: tests/test_pc2_checkpoint.py
    with pytest.raises(
        ValueError,
        match=r"with_cfg\.pth could run code from the file while loading \(it calls (tests\.)?test_pvcnn2\._Config\)",
    ):
        load_reference_checkpoint(with_cfg, "pc2")


@pytest.mark.parametrize("mask_channels", [True, False])  # PC²'s Co3D inputs; BDM's ShapeNet ones
def test_cdm_network_feeds_pvcnn2_pc2s_channel_order(tiny, mask_channels: bool):
    cfg = tiny.replace(
        **{
            "model.denoiser": "pvcnn2",
            "model.width_multiplier": 0.25,
            "model.voxel_resolution_multiplier": 0.25,
            "model.mask_channels": mask_channels,
        }
    )
    net = CDMNetwork(cfg.model, prior_2d_channels=1)
    f = cfg.model.feature_dim
    assert isinstance(net.denoiser, PVCNN2Denoiser)
    assert net.denoiser.in_channels == conditioning_channels(f, 1, cfg.model.mask_channels)
    batch = tiny_batch(n=300)
    context = net.encode(batch)
    features = net.encoder(batch.image, batch.mask, batch.prior_2d)
    # PC²'s projection_model.py: RGB normalised to [-1, 1], image features, mask, distance; the prior after
    # the features.
    # The features stay coarse in the context; projection inserts them after RGB.
    pc2 = [batch.image * 2 - 1, features, batch.prior_2d, batch.mask, mask_distance_transform(batch.mask)]
    assert torch.equal(upsample_features(context.features, 16), features)
    assert torch.equal(context.pixel, torch.cat([pc2[0], *pc2[2 : 5 if cfg.model.mask_channels else 3]], dim=1))
    out = net(batch.points, torch.tensor([0, 999]), context, batch.camera)
    assert out.shape == (2, 300, 3) and torch.isfinite(out).all()


def test_cross_attention_at_the_bottleneck_starts_as_pc2s_function_and_then_reads_the_tokens():
    torch.manual_seed(3)
    plain = PVCNN2Denoiser(2, width_multiplier=0.25, voxel_resolution_multiplier=0.25).eval()
    attending = PVCNN2Denoiser(
        2, width_multiplier=0.25, voxel_resolution_multiplier=0.25, token_channels=8, num_tokens=4
    ).eval()
    attending.load_state_dict(plain.state_dict(), strict=False)  # the same PC² weights, plus the new block
    extra = {k for k in attending.state_dict()} - {k for k in plain.state_dict()}
    assert extra and all(k.startswith("cross_att.") for k in extra)
    with torch.no_grad():
        for model in (plain, attending):
            model.classifier[-1].weight.normal_(0, 0.1, generator=torch.Generator().manual_seed(4))
    x_t, cond, t = torch.randn(1, 300, 3), torch.randn(1, 300, 2), torch.tensor([10])
    tokens = torch.randn(1, 4, 8)
    with torch.no_grad():
        assert torch.equal(plain(x_t, cond, t), attending(x_t, cond, t, tokens))  # zero-initialised output projection
        attending.cross_att.attn.out_proj.weight.normal_(0, 0.1)
        moved = attending(x_t, cond, t, tokens) - attending(x_t, cond, t, tokens.flip(1).roll(1, dims=2))
    assert moved.abs().max() > 1e-4


def test_the_category_prior_with_pvcnn2_is_pvds_network(tiny):
    cfg = tiny.replace(**{"model.denoiser": "pvcnn2", "model.time_embed_dim": 64})  # PVD's embed_dim
    prior = PriorNetwork(cfg.model, device="cpu")
    assert [(n, tuple(p.shape)) for n, p in prior.denoiser.named_parameters()] == pc2_parameters(3)
    g = torch.Generator().manual_seed(5)
    ckpt = {"model_state": {"model.module." + n: torch.randn(s, generator=g) * 0.01 for n, s in pc2_parameters(3)}}
    load_reference_weights(prior.denoiser, reference_state_dict(ckpt, "pvd"))
    out = prior.eval()(torch.randn(1, 256, 3, generator=g), torch.tensor([500]))
    assert out.shape == (1, 256, 3) and torch.isfinite(out).all()


def test_a_pvd_checkpoint_file_is_a_blending_prior_with_pvds_schedule(tmp_path):
    from cdm.prior_model import load_prior

    g = torch.Generator().manual_seed(7)
    weights = {"model.module." + n: torch.randn(s, generator=g) * 0.01 for n, s in pc2_parameters(3)}
    torch.save({"epoch": 1999, "model_state": weights, "optimizer_state": {}}, tmp_path / "chair.pth")
    prior = load_prior(tmp_path / "chair.pth", category="chair")
    assert prior.category == "chair" and not prior.network.training
    assert torch.equal(prior.network.denoiser.sa_layers[0][0].voxel_layers[0].weight,
                       weights["model.module.sa_layers.0.0.voxel_layers.0.weight"])
    # PVD's schedule (BDM experiments/pvd/__init__.py): linear β 1e-4 → 0.02 over 1,000 steps, ε-prediction.
    assert prior.diffusion.betas[0].item() == pytest.approx(1e-4) and prior.diffusion.betas[-1].item() == pytest.approx(
        0.02
    )
    assert len(prior.diffusion.betas) == 1000 and prior.diffusion.prediction == "eps"
    torch.save({"model_state": {k: v for k, v in list(weights.items())[1:]}}, tmp_path / "broken.pth")
    with pytest.raises(ValueError, match=r"sampling\.blend\.prior_checkpoint: .*broken\.pth: not a PVD checkpoint"):
        load_prior(tmp_path / "broken.pth", category="chair")


def test_pc2_timestep_embedding_divides_by_half_minus_one():
    emb = pc2_timestep_embedding(torch.tensor([0, 7]), 8)
    freqs = torch.exp(
        -torch.arange(4, dtype=torch.float64) * torch.log(torch.tensor(10_000.0, dtype=torch.float64)) / 3
    )
    assert torch.equal(emb[0], torch.tensor([0.0] * 4 + [1.0] * 4))
    torch.testing.assert_close(emb[1], torch.cat([torch.sin(7 * freqs), torch.cos(7 * freqs)]).float())


def test_voxel_attention_is_unscaled_softmax_attention():
    # PC²'s modules/pvconv.py Attention: qk = qᵀk with the 1/√C commented out, h = v wᵀ, out, residual, GN, Swish.
    torch.manual_seed(6)
    att = SelfAttention(8, 3).double()
    x = torch.randn(2, 8, 2, 3, 2, dtype=torch.float64)
    flat = x.flatten(2)
    q, k, v = (torch.einsum("oc,bcl->bol", p.weight.flatten(1), flat) + p.bias[:, None] for p in (att.q, att.k, att.v))
    w = torch.softmax(torch.einsum("bci,bcj->bij", q, k), dim=-1)
    h = torch.einsum("bcj,bij->bci", v, w)
    h = torch.einsum("oc,bcl->bol", att.out.weight.flatten(1), h) + att.out.bias[:, None]
    ref = torch.nn.functional.silu(att.norm(h.view_as(x) + x))
    torch.testing.assert_close(att(x), ref)
