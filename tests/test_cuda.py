"""The CUDA paths against the CPU: every op of :mod:`cdm.model.pointops`, a pvcnn2 training step, the evaluation.

Each test computes the same thing on the CPU and on CUDA and compares: index results identical, float
results equal to float32 rounding (sums run in another order on the GPU: atomics, tree reductions).
TF32 is switched off while they run, so a convolution on the GPU rounds as float32 does. Where no CUDA
device is present every test here is skipped, with that reason; run them on a GPU with
``python -m pytest tests/test_cuda.py``.
"""

from __future__ import annotations

import copy

import pytest
import torch

from cdm.checkpoint import load_checkpoint
from cdm.config import TrainConfig
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.diffusion import GaussianDiffusion, SamplerSettings
from cdm.evaluate import build_eval_set, run_evaluation
from cdm.metrics import chamfer_f1
from cdm.model import CDMNetwork, pointops
from cdm.model.conditioning import features_at_pixels
from cdm.model.pvcnn import point_norm_silu
from cdm.model.voxels import SparseGrid, VoxelBranch, normalize_coords
from cdm.optim import Optimiser
from cdm.render import splat_points
from cdm.train import Trainer
from tests.conftest import tiny_config
from tests.test_model import tiny_batch

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device here: the CUDA paths are compared with the CPU where one is present",
)
CUDA = torch.device("cuda")
RTOL, ATOL = 1e-5, 1e-6  # float32 rounding of sums of a few hundred terms of order 1


@pytest.fixture(autouse=True)
def _float32_on_the_gpu():
    """TF32 keeps 10 mantissa bits: a GPU convolution would differ from the CPU's by far more than rounding."""
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def _cloud(b: int, n: int, seed: int) -> torch.Tensor:
    return torch.rand(b, 3, n, generator=torch.Generator().manual_seed(seed)) * 2.0 - 1.0


def _dyadic_cloud(b: int, n: int, seed: int) -> torch.Tensor:
    """``n / 2`` points of coordinates k/16 (|k| ≤ 16) and their mirror images: the mean is exactly 0 and
    every squared norm exact in float32, whatever the summation order or the mean's formula (the CPU
    divides the sum by N, CUDA multiplies by 1/N), so the voxel a point falls in cannot depend on the device."""
    half = torch.randint(-16, 17, (b, 3, n // 2), generator=torch.Generator().manual_seed(seed)).float() / 16.0
    return torch.cat([half, -half], dim=2)


@pytest.mark.parametrize("n", [700, 3000])  # below and above the FPS kernel's 512 threads (its tie order)
def test_farthest_point_sample_picks_the_same_points(n):
    coords = _cloud(2, n, 0)
    coords[:, :, n // 2 :] = coords[:, :, : n - n // 2]  # duplicated points: ties the tie-break must settle alike
    cpu = pointops.farthest_point_sample(coords, 256)
    assert torch.equal(pointops.farthest_point_sample(coords.to(CUDA), 256).cpu(), cpu)


def test_ball_query_finds_the_same_neighbours():
    points = _cloud(2, 2000, 1)
    centers = pointops.gather_points(points, pointops.farthest_point_sample(points, 300))
    for radius, k in ((0.1, 32), (0.4, 64)):
        cpu = pointops.ball_query(centers, points, radius, k)
        assert torch.equal(pointops.ball_query(centers.to(CUDA), points.to(CUDA), radius, k).cpu(), cpu)


def test_gather_and_group_give_the_same_features_and_gradients():
    points = _cloud(2, 500, 2)
    features = torch.randn(2, 16, 500, generator=torch.Generator().manual_seed(3), requires_grad=True)
    index = pointops.ball_query(points[:, :, :64], points, 0.3, 16)
    centres = pointops.farthest_point_sample(points, 64)
    f_gpu = features.detach().to(CUDA).requires_grad_()
    cpu = pointops.group(features, index)
    gpu = pointops.group(f_gpu, index.to(CUDA))
    assert torch.equal(gpu.detach().cpu(), cpu.detach())  # a gather copies: bit for bit
    assert torch.equal(pointops.gather_points(f_gpu, centres.to(CUDA)).detach().cpu(),
                       pointops.gather_points(features, centres).detach())
    weights = torch.randn(cpu.shape, generator=torch.Generator().manual_seed(4))
    (cpu * weights).sum().backward()
    (gpu * weights.to(CUDA)).sum().backward()  # repeated neighbours: summed by atomics on the GPU
    torch.testing.assert_close(f_gpu.grad.cpu(), features.grad, rtol=RTOL, atol=ATOL)


def test_three_nn_and_its_interpolation_agree():
    points, centers = _cloud(2, 1500, 5), _cloud(2, 200, 6)
    cpu = pointops.three_nn(points, centers)
    gpu = pointops.three_nn(points.to(CUDA), centers.to(CUDA))
    assert torch.equal(gpu.index.cpu(), cpu.index)
    torch.testing.assert_close(gpu.weight.cpu(), cpu.weight, rtol=RTOL, atol=ATOL)
    features = torch.randn(2, 8, 200, generator=torch.Generator().manual_seed(7), requires_grad=True)
    f_gpu = features.detach().to(CUDA).requires_grad_()
    out = pointops.three_nn_interpolate(points, centers, features)
    out_gpu = pointops.three_nn_interpolate(points.to(CUDA), centers.to(CUDA), f_gpu)
    torch.testing.assert_close(out_gpu.detach().cpu(), out.detach(), rtol=RTOL, atol=ATOL)
    out.square().sum().backward()
    out_gpu.square().sum().backward()
    torch.testing.assert_close(f_gpu.grad.cpu(), features.grad, rtol=RTOL, atol=1e-5)


@pytest.mark.parametrize("resolution", [8, 32])
def test_voxelize_and_devoxelize_agree(resolution):
    points = _dyadic_cloud(2, 1000, 8)
    cpu = pointops.voxelize_coords(points, resolution)
    gpu = pointops.voxelize_coords(points.to(CUDA), resolution)
    assert torch.equal(gpu.voxel.cpu(), cpu.voxel) and torch.equal(gpu.count.cpu(), cpu.count)
    torch.testing.assert_close(gpu.coords.cpu(), cpu.coords, rtol=0, atol=0)
    features = torch.randn(2, 12, 1000, generator=torch.Generator().manual_seed(9), requires_grad=True)
    f_gpu = features.detach().to(CUDA).requires_grad_()
    voxels, voxels_gpu = pointops.voxelize(features, cpu), pointops.voxelize(f_gpu, gpu)
    torch.testing.assert_close(voxels_gpu.detach().cpu(), voxels.detach(), rtol=RTOL, atol=ATOL)  # atomics' order
    back = pointops.trilinear_devoxelize(voxels, cpu)
    back_gpu = pointops.trilinear_devoxelize(voxels_gpu, gpu)
    torch.testing.assert_close(back_gpu.detach().cpu(), back.detach(), rtol=RTOL, atol=ATOL)
    back.square().sum().backward()
    back_gpu.square().sum().backward()
    torch.testing.assert_close(f_gpu.grad.cpu(), features.grad, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_the_sparse_voxel_branch_agrees(precision):
    """Kernel map, submanifold convolution, norm and trilinear devoxelisation of the sparse back-end; under
    fp16 autocast the convolution's products run in half precision on CUDA (float32 on the CPU)."""
    coords = normalize_coords(_dyadic_cloud(2, 1000, 10).transpose(1, 2))
    cpu, gpu = SparseGrid(coords, 8), SparseGrid(coords.to(CUDA), 8)
    for name in ("out_rows", "in_rows"):
        assert torch.equal(getattr(gpu.kernel_map, name).cpu(), getattr(cpu.kernel_map, name)), name
    assert gpu.kernel_map.bounds == cpu.kernel_map.bounds
    torch.manual_seed(0)
    branch = VoxelBranch(12, 16, 8)
    branch_gpu = copy.deepcopy(branch).to(CUDA)
    features = torch.randn(2, 1000, 12, generator=torch.Generator().manual_seed(11), requires_grad=True)
    f_gpu = features.detach().to(CUDA).requires_grad_()
    out = branch(features, cpu)
    with torch.autocast("cuda", dtype=torch.float16, enabled=precision == "fp16"):
        out_gpu = branch_gpu(f_gpu, gpu)
    out.square().sum().backward()
    out_gpu.float().square().sum().backward()
    pairs = [(out_gpu.detach().float(), out.detach()), (f_gpu.grad, features.grad)]
    pairs += [(p_gpu.grad, p.grad) for p, p_gpu in zip(branch.parameters(), branch_gpu.parameters())]
    for got, expected in pairs:
        assert got.dtype == expected.dtype
        if precision == "fp32":
            torch.testing.assert_close(got.cpu(), expected, rtol=1e-4, atol=1e-5)
        else:  # fp16 keeps 11 bits: sums of a few hundred products stay within 1 % of the largest value
            assert (got.cpu() - expected).abs().max() <= 1e-2 * expected.abs().max()


def _pvcnn2_config(tmp_path, **overrides):
    return tiny_config(tmp_path, **{"model.denoiser": "pvcnn2", "model.width_multiplier": 0.25,
                                    "model.voxel_resolution_multiplier": 0.5, "data.num_points": 1024, **overrides})


def test_lean_step_ops_match_the_cpus():
    """The training step's hand-written pieces (benchmarks/RESULTS.md, "Lean local step"): point
    GroupNorm+SiLU, features sampled at pixels and the splat's footprint filter, values and gradients."""
    g = torch.Generator().manual_seed(0)
    h = torch.randn(2, 300, 32, generator=g) * 3 + 5
    norm = torch.nn.GroupNorm(8, 32)
    coarse = torch.randn(2, 6, 8, 8, generator=g)
    pixel = torch.randint(0, 256, (2, 300), generator=g)
    points = torch.rand(2, 300, 3, generator=g) - 0.5
    cams = tiny_batch(b=2).camera

    def run(device: torch.device) -> list[torch.Tensor]:
        net = copy.deepcopy(norm).to(device)
        inputs = [t.to(device).requires_grad_() for t in (h, coarse, points)]
        cameras = cams.to(device)
        outs = [point_norm_silu(inputs[0], net), features_at_pixels(inputs[1], pixel.to(device), 16),
                splat_points(inputs[2], cameras, 32, 0.06, "planar")]
        loss = sum((o * torch.linspace(-1, 1, o.numel(), device=device).view_as(o)).sum() for o in outs)
        return [o.detach().cpu() for o in outs] + [x.cpu() for x in torch.autograd.grad(loss, [*inputs, net.weight])]

    for got, want in zip(run(CUDA), run(torch.device("cpu")), strict=True):
        torch.testing.assert_close(got, want, rtol=RTOL, atol=ATOL * max(1.0, want.abs().max().item()))


def test_a_pvcnn2_training_step_matches_the_cpus(tmp_path):
    """One step of the real pieces (network, loss, optimiser) on both devices from the same weights, batch,
    timesteps and noise. Dropout off (eval mode): its masks come from each device's own generator. x_t is
    made once, on the CPU: farthest-point sampling on coordinates an ulp apart could pick another centre
    at a near-tie, and the outputs would differ by more than rounding."""
    cfg = _pvcnn2_config(tmp_path)
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)
    torch.manual_seed(0)
    net = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d], device="cpu").eval()
    net_gpu = copy.deepcopy(net).to(CUDA)
    batch = tiny_batch(b=2, n=1024, s=cfg.data.image_size, prior_channels=PRIOR_2D_CHANNELS[cfg.priors.prior_2d])
    g = torch.Generator().manual_seed(1)
    t = torch.randint(0, diffusion.num_steps, (2,), generator=g)
    noise = torch.randn(batch.points.shape, generator=g)
    train = TrainConfig(lr=1e-3, warmup_steps=0, steps=10)

    x_t = diffusion.q_sample(batch.points, t, noise)

    def step(network, b, x_t, t, noise):
        out = network(x_t, t, network.encode(b), b.camera)
        loss = diffusion.loss(out, b.points, noise, t)
        Optimiser(network.parameters(), train, "fp32", b.points.device.type).step(loss)
        return out.detach().cpu(), loss.item()

    out, loss = step(net, batch, x_t, t, noise)
    out_gpu, loss_gpu = step(net_gpu, batch.to(CUDA), x_t.to(CUDA), t.to(CUDA), noise.to(CUDA))
    torch.testing.assert_close(out_gpu, out, rtol=1e-4, atol=1e-6)  # through ~20 layers: a few roundings each
    assert loss_gpu == pytest.approx(loss, rel=1e-4)
    for (name, p), p_gpu in zip(net.named_parameters(), net_gpu.parameters()):
        torch.testing.assert_close(p_gpu.detach().cpu(), p.detach(), rtol=1e-4, atol=1e-6, msg=name)


@pytest.mark.parametrize("precision", ["fp32", "fp16", "bf16"])
def test_pvcnn2_trains_on_cuda_in_every_precision(tmp_path, precision):
    trainer = Trainer(_pvcnn2_config(tmp_path, **{"train.device": "cuda", "train.precision": precision}))
    assert trainer.precision == precision and trainer.optimiser.scaler.is_enabled() == (precision == "fp16")
    steps = [trainer.train_step(trainer.next_batch()) for _ in range(6)]
    assert all(torch.isfinite(torch.tensor(s.total)) for s in steps)
    # fp16 may skip its first steps while the loss scale falls from 2¹⁶ to what the gradients allow
    assert sum(not s.skipped for s in steps) >= (1 if precision == "fp16" else 6)


def test_sampling_steps_and_metrics_match_the_cpus(tmp_path):
    """Each DDIM step (no noise) from the same x on both devices, the CPU's result carried on (a chain run
    apart would let farthest-point sampling meet a near-tie); then CD and F1 of the same clouds."""
    cfg = _pvcnn2_config(tmp_path)
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)
    torch.manual_seed(0)
    net = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d], device="cpu").eval()
    with torch.no_grad():  # PC²'s head starts at N(0, 1e-6): an output of some size exercises the update
        net.denoiser.classifier[-1].weight.normal_(0, 0.1)
    net_gpu = copy.deepcopy(net).to(CUDA)
    batch = tiny_batch(b=2, n=1024, s=cfg.data.image_size, prior_channels=PRIOR_2D_CHANNELS[cfg.priors.prior_2d])
    batch_gpu = batch.to(CUDA)
    settings = SamplerSettings(sampler="ddim", steps=5, clip_x0=1.0)
    timesteps = diffusion.timesteps(settings)
    x = torch.randn(batch.points.shape, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        context, context_gpu = net.encode(batch), net_gpu.encode(batch_gpu)
        for i, step in enumerate(timesteps):
            t = torch.full((2,), step, dtype=torch.long)
            nxt = diffusion.step(x, t, i, timesteps, diffusion.predict_x0(x, t, net(x, t, context, batch.camera)),
                                 settings, None)
            x_gpu, t_gpu = x.to(CUDA), t.to(CUDA)
            out_gpu = net_gpu(x_gpu, t_gpu, context_gpu, batch_gpu.camera)
            nxt_gpu = diffusion.step(
                x_gpu, t_gpu, i, timesteps, diffusion.predict_x0(x_gpu, t_gpu, out_gpu), settings, None
            )
            torch.testing.assert_close(nxt_gpu.cpu(), nxt, rtol=1e-4, atol=1e-5, msg=f"step {i} (t = {step})")
            x = nxt
    cpu = chamfer_f1(x, batch.points)  # scipy's KD-tree on the CPU, the brute-force search on CUDA
    gpu = chamfer_f1(x.to(CUDA), batch.points.to(CUDA))
    torch.testing.assert_close(gpu.cd.cpu(), cpu.cd, rtol=1e-4, atol=1e-7)
    # A point whose squared distance rounds across the threshold moves precision or recall by 1/1024.
    torch.testing.assert_close(gpu.f1.cpu(), cpu.f1, rtol=0, atol=2.0 / 1024)


def test_evaluation_runs_on_cuda_with_the_cpus_evaluation_set(tmp_path):
    """The whole evaluation on CUDA: the same objects and baselines as the CPU's (they are device-free),
    finite scores; the samples differ, since each device's generator draws its own noise."""
    cfg = _pvcnn2_config(tmp_path, **{"train.device": "cuda", "eval.num_objects": 2, "diffusion.sample_steps": 3})
    trainer = Trainer(cfg)
    eval_set = build_eval_set(cfg, trainer.val_set, trainer.train_set, cfg.eval.seed)
    gpu = run_evaluation(trainer.network, trainer.diffusion, eval_set, cfg, CUDA, tmp_path / "gpu")
    cpu = run_evaluation(
        copy.deepcopy(trainer.network).cpu(), trainer.diffusion, eval_set, cfg, torch.device("cpu"), None
    )
    assert [r["object_id"] for r in gpu.rows] == [r["object_id"] for r in cpu.rows]
    assert {k: v for k, v in gpu.metrics.items() if k.startswith("baseline/")} == \
        {k: v for k, v in cpu.metrics.items() if k.startswith("baseline/")}
    assert all(torch.isfinite(torch.tensor(v)) for v in gpu.metrics.values())
    assert (tmp_path / "gpu" / "objects.csv").is_file()


def test_fp16_loss_scale_travels_with_the_checkpoint(tmp_path):
    cfg = _pvcnn2_config(tmp_path, **{"train.device": "cuda", "train.precision": "fp16", "train.steps": 3,
                                      "train.eval_every": 3, "eval.num_objects": 1, "diffusion.sample_steps": 2})
    trainer = Trainer(cfg)
    for _ in range(3):
        trainer.train_step(trainer.next_batch())
    saved = load_checkpoint(trainer.save_checkpoint())
    assert saved.precision == "fp16" and saved.loss_scale["scale"] == trainer.optimiser.scaler.get_scale()
    resumed = Trainer(cfg.replace(**{"train.steps": 4}))
    resumed.restore(saved)
    assert resumed.optimiser.scaler.get_scale() == trainer.optimiser.scaler.get_scale() <= 2.0**16


def test_mask_distance_transform_and_the_front_layer_minimum_match_the_cpu():
    """The distance transform gives the CPU's values on CUDA; the
    window minimum runs ``max_pool2d`` on CUDA and kornia's erosion on the CPU: the same values."""
    from cdm.model.conditioning import mask_distance_transform
    from cdm.render import _window_min

    g = torch.Generator().manual_seed(0)
    mask = (torch.rand(3, 1, 40, 40, generator=g) < 0.05).float()
    gpu = mask_distance_transform(mask.to(CUDA))
    assert gpu.device.type == "cuda" and torch.equal(gpu.cpu(), mask_distance_transform(mask))
    zbuf = torch.rand(4, 1, 30, 30, generator=g) + 2.0
    zbuf[torch.rand(zbuf.shape, generator=g) < 0.6] = float("inf")
    for half in (1, 4):
        assert torch.equal(_window_min(zbuf.to(CUDA), half).cpu(), _window_min(zbuf, half))
