"""The CDM training loop, readable top to bottom: ``fit(config, callbacks)``.

One step: the loss of Eq. 6 (:func:`cdm.objective.cdm_loss`: diffusion term + λ × the 3D prior
constraint) and one optimiser step (:class:`cdm.optim.Optimiser`: AdamW, warm-up + cosine, clip).

The loop talks to the outside only through :class:`Callback` (sweeps/ hooks Ray and MLflow in
there). Checkpoints (:mod:`cdm.checkpoint`) carry the resolved config, the step, the voxel back-end
and every RNG state, so
``fit(config, resume_from=dir)`` continues with exactly the step the interrupted run would have taken.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch
import torch.distributed
from torch.utils.data import DataLoader

from cdm.checkpoint import Checkpoint, checkpoint_file, load_checkpoint, save_step
from cdm.config import Config
from cdm.data import build_dataset
from cdm.data.order import ByRound, StepBatches, batch_indices
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.data.sample import Batch, collate
from cdm.diffusion import GaussianDiffusion
from cdm.evaluate import EvalSet, build_eval_set, run_evaluation
from cdm.external_inputs import check_coverage, check_inputs
from cdm.io.write import check_within, make_folder
from cdm.metric_names import COMPUTE_METRIC, TRAIN_METRICS
from cdm.model import CDMNetwork, check_encoder_record
from cdm.objective import LossTerms, cdm_loss
from cdm.optim import MAX_SKIPPED_IN_A_ROW, Optimiser, TrainingDiverged, check_like
from cdm.provenance import run_record
from cdm.runtime import AUTOCAST_DTYPES, resolve_precision, start_run
from cdm.shared import SharedStore, SharedViews

__all__ = ["Callback", "FitResult", "StepLosses", "Trainer", "TrainingDiverged", "fit"]

log = logging.getLogger(__name__)


class Callback:
    """Hooks of :func:`fit`; every method is a no-op here. Subclass and override what you need."""

    def on_start(self, record: dict[str, str]) -> None:
        """Once, before the first step: the reproducibility record (:func:`cdm.provenance.run_record`)."""

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        """Every ``train.log_every`` steps: ``train/*`` running means since the last call."""

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        """After each evaluation: ``eval/*`` and ``baseline/*`` metrics, PLY/PNG/CSV files written."""

    def on_checkpoint(self, step: int, path: Path) -> None:
        """A complete checkpoint folder (:mod:`cdm.checkpoint`) was written at ``path``."""

    def should_stop(self) -> bool:
        """Polled every step; ``True`` ends training after the current step (no final evaluation)."""
        return False


class StepLosses(NamedTuple):
    """One training step: the loss of Eq. 6, its two terms, and whether mixed precision skipped the step."""

    total: float
    diffusion: float
    prior_3d: float
    skipped: bool


@dataclass
class FitResult:
    """Where training ended: last step, last evaluation's metrics and the last checkpoint."""

    step: int
    metrics: dict[str, float]
    checkpoint_dir: Path | None


def _check_compatible(state: Checkpoint, config: Config, network: CDMNetwork) -> None:
    check_encoder_record(state.encoder, network.encoder.record)
    if state.voxel_backend != network.voxel_backend:
        raise ValueError(
            f"resume: checkpoint trained with voxel back-end {state.voxel_backend!r}, this run resolves to "
            f"{network.voxel_backend!r}; set model.voxel_backend={state.voxel_backend} "
            "(the back-ends compute different functions)"
        )
    saved, now = state.config, config.to_dict()
    # The resolved back-end is compared above; `auto` and its resolution may be written either way.
    differ = [f"model.{k}" for k in now["model"] if k != "voxel_backend" and saved["model"].get(k) != now["model"][k]]
    differ += [f"diffusion.{k}" for k in now["diffusion"] if saved["diffusion"].get(k) != now["diffusion"][k]]
    differ += [f"data.{k}" for k in ("num_points", "image_size") if saved["data"].get(k) != now["data"][k]]
    if differ:
        raise ValueError(
            f"resume: this run's {', '.join(differ)} differ from the checkpoint's; resume with the same settings"
        )


class ComputeClock:
    """Seconds of compute a run's training has spent (``train.compute_budget_s``'s unit): on CPU this process's
    CPU seconds (``time.process_time``, all its threads: a run waiting for a shared core spends none); on CUDA
    wall seconds, the device synchronised before each reading so queued kernels count. :meth:`paused` leaves a
    span out (evaluation)."""

    def __init__(self, device: torch.device, spent: float = 0.0):
        self.device = device
        self.spent = spent
        self._since = self._now()

    def _now(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            return time.perf_counter()
        return time.process_time()

    def seconds(self) -> float:
        """Seconds spent so far, the running span included."""
        return self.spent + self._now() - self._since

    @contextmanager
    def paused(self) -> Iterator[None]:
        """Inside, no compute is counted (and :meth:`seconds` stays where it was)."""
        self.spent = self.seconds()
        self._since = self._now()
        yield
        self._since = self._now()


class Trainer:
    """State of one run: data, network, optimiser, RNGs and step. :func:`fit` drives it; benchmarks and
    the sweep runner's cost estimate time its steps directly."""

    def __init__(self, config: Config, shared: SharedStore | None = None):
        self.cfg = config
        self.shared = shared
        self.device = start_run(config.train)
        check_inputs(config)
        self.train_set = build_dataset(config, "train")
        self.val_set = build_dataset(config, "val")
        check_coverage(config, (self.train_set, self.val_set))
        # Where a store holds this data's rendered rounds (a sweep's cells share them), batches read them.
        self._samples = self.train_set if shared is None else SharedViews(shared, config, self.train_set)
        self.precision = resolve_precision(config.train.precision, self.device)
        self.network = CDMNetwork(config.model, PRIOR_2D_CHANNELS[config.priors.prior_2d], device=self.device,
                                  autocast=AUTOCAST_DTYPES[self.precision]).to(self.device)
        log.info(
            "voxel back-end: %s (model.voxel_backend=%s, device %s)",
            self.network.voxel_backend, config.model.voxel_backend, self.device,
        )
        self.ema = _ema_copy(self.network) if config.train.ema_decay is not None else None
        self.diffusion = GaussianDiffusion.from_config(config.diffusion)
        t = config.train
        self.optimiser = Optimiser(self.network.parameters(), t, self.precision, self.device.type)
        # Data-parallel when a process group exists (Ray Train's TorchTrainer sets one up): each rank
        # draws its own batch and noise, and gradients are averaged before the optimiser step.
        distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
        self.rank = torch.distributed.get_rank() if distributed else 0
        self.world = torch.distributed.get_world_size() if distributed else 1
        self.generator = torch.Generator(device=self.device).manual_seed(t.seed + 7919 * self.rank)
        self.step = 0
        self.compute_s = 0.0
        """Seconds of compute spent at the last evaluation (:class:`ComputeClock`), saved with each checkpoint."""
        self.out_dir = Path(config.train.out_dir)
        self._eval_set: EvalSet | None = None
        self._loader: Iterator[Batch] | None = None
        self._loader_step = 0

    def state(self) -> Checkpoint:
        return Checkpoint(
            config=self.cfg.to_dict(),
            step=self.step,
            compute_s=self.compute_s,
            voxel_backend=self.network.voxel_backend,
            precision=self.precision,
            loss_scale=self.optimiser.scaler.state_dict() if self.optimiser.scaler.is_enabled() else None,
            encoder=self.network.encoder.record,
            model=self.network.state_dict(),
            ema=None if self.ema is None else self.ema.state_dict(),
            optimizer=self.optimiser.optimizer.state_dict(),
            scheduler=self.optimiser.scheduler.state_dict(),
            generator=self.generator.get_state(),
            torch_rng=torch.get_rng_state(),
        )

    def restore(self, state: Checkpoint, label: str = "resume") -> None:
        """Continue from ``state``; ``label`` starts a refusal (``resume: <its file>``)."""
        if state.kind is not None:
            raise ValueError(f"resume: the checkpoint holds a {state.kind} ({state.category}), not a CDM run")
        _check_compatible(state, self.cfg, self.network)
        self.network.load_state_dict(state.model)
        if self.ema is not None:
            # A checkpoint from a run without EMA starts the average at its weights, not at init.
            self.ema.load_state_dict(state.weights)
        self.optimiser.restore(state.optimizer, state.scheduler, label)
        trained = state.precision or "fp32"  # checkpoints before train.precision trained in fp32
        if trained != self.precision:
            # Precision changes the rounding, not the function: continue, and say so (train.precision).
            log.warning("resume: the checkpoint trained in %s, this run continues in %s (train.precision)",
                        trained, self.precision)
        elif state.loss_scale is not None:
            check_like(state.loss_scale, self.optimiser.scaler.state_dict(), f"{label}: its loss scale")
            self.optimiser.scaler.load_state_dict(state.loss_scale)
        check_like(state.generator, self.generator.get_state(), f"{label}: its noise generator state")
        check_like(state.torch_rng, torch.get_rng_state(), f"{label}: its torch RNG state")
        check_like(state.step, 0, f"{label}: its step")
        self.generator.set_state(state.generator)
        torch.set_rng_state(state.torch_rng)
        self.step = state.step
        self.compute_s = float(state.compute_s)

    def next_batch(self) -> Batch:
        if self.cfg.data.num_workers == 0:
            idx = batch_indices(
                self.step * self.world + self.rank, self.cfg.train.batch_size, len(self.train_set), self.cfg.train.seed
            )
            return collate([self._samples.sample(i, epoch) for epoch, i in idx]).to(self.device)
        # Workers decode the coming steps' batches while this one trains. The batches are the same
        # function of the step as above, so results do not depend on data.num_workers; a loader is
        # (re)started at the current step, e.g. after a resume.
        if self._loader is None or self._loader_step != self.step:
            sampler = StepBatches(self.step, self.cfg.train.steps, self.world, self.rank, self.cfg.train.batch_size,
                                  len(self.train_set), self.cfg.train.seed)
            self._loader = iter(DataLoader(ByRound(self._samples), batch_sampler=sampler, collate_fn=collate,
                                           num_workers=self.cfg.data.num_workers))
            self._loader_step = self.step
        self._loader_step += 1
        return next(self._loader).to(self.device)

    def losses(self, batch: Batch) -> LossTerms:
        """Total loss, diffusion term and 3D prior term (Eq. 6) for one batch (:func:`cdm.objective.cdm_loss`)."""
        return cdm_loss(network=self.network, diffusion=self.diffusion, batch=batch, priors=self.cfg.priors,
                        generator=self.generator, diverged=self._diverged)

    def _diverged(self, what: str) -> TrainingDiverged:
        return TrainingDiverged(
            f"{what} became NaN or infinite at step {self.step}; lower train.lr (now {self.cfg.train.lr}) "
            f"or priors.lambda_3d (now {self.cfg.priors.lambda_3d})"
        )

    def train_step(self, batch: Batch) -> StepLosses:
        """One batch: loss, backward, optimiser step (skipped in mixed precision when a gradient is not
        finite: the step counter still advances, the batch is spent, as in PC²'s Accelerate loop)."""
        loss, loss_diff, loss_prior = self.losses(batch)
        if not torch.isfinite(loss):
            raise self._diverged("the 3D prior loss")
        stepped = self.optimiser.step(loss, self._average_gradients if self.world > 1 else None)
        if not stepped and self.optimiser.skipped_in_a_row >= MAX_SKIPPED_IN_A_ROW:
            raise self._diverged(f"every gradient of the last {MAX_SKIPPED_IN_A_ROW} steps ({self.precision})")
        if self.ema is not None:
            _ema_update(self.ema, self.network, self.cfg.train.ema_decay)
        self.step += 1
        return StepLosses(loss.item(), loss_diff.item(), loss_prior.item(), not stepped)

    def _average_gradients(self) -> None:
        """Mean of every gradient over ranks: the same update everywhere, as DDP would make it."""
        grads = [p.grad for p in self.network.parameters() if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads])
        torch.distributed.all_reduce(flat)
        flat /= self.world
        offset = 0
        for g in grads:
            g.copy_(flat[offset : offset + g.numel()].view_as(g))
            offset += g.numel()

    def evaluate(self) -> tuple[dict[str, float], list[Path]]:
        if self._eval_set is None:
            self._eval_set = (
                build_eval_set(self.cfg, self.val_set, self.train_set, self.cfg.eval.seed)
                if self.shared is None
                else self.shared.eval_set(self.cfg, self.val_set, self.train_set)
            )
        network = self.ema if self.ema is not None else self.network
        out = run_evaluation(
            network,
            self.diffusion,
            self._eval_set,
            self.cfg,
            self.device,
            make_folder(self.out_dir / "eval" / f"step_{self.step:07d}", "train.out_dir", within=self.out_dir),
        )
        return out.metrics, out.files

    def agreed(self, seconds: float) -> float:
        """``seconds`` of compute as every rank reads them (the most of any): ranks stop and evaluate at the same
        step, so none waits in a collective the others left."""
        if self.world == 1:
            return seconds
        value = torch.tensor([seconds], dtype=torch.float64, device=self.device)
        torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX)
        return float(value.item())

    def save_checkpoint(self, keep: int = 2) -> Path:
        return save_step(self.state(), self.out_dir, keep)


def _ema_copy(network: CDMNetwork) -> CDMNetwork:
    ema = copy.deepcopy(network)
    ema.requires_grad_(False)
    return ema


@torch.no_grad()
def _ema_update(ema: torch.nn.Module, network: torch.nn.Module, decay: float) -> None:
    for e, p in zip(ema.parameters(), network.parameters()):
        e.lerp_(p, 1.0 - decay)
    for e, b in zip(ema.buffers(), network.buffers()):
        e.copy_(b)


def _evaluate_and_save(trainer: Trainer, callbacks: Sequence[Callback], compute_s: float = 0.0
                       ) -> tuple[dict[str, float], Path]:
    """Evaluate, then checkpoint, telling the callbacks of each; the metrics carry ``compute_s``, the seconds of
    compute training has spent so far (:data:`cdm.metric_names.COMPUTE_METRIC`)."""
    metrics, files = trainer.evaluate()
    metrics[COMPUTE_METRIC] = trainer.compute_s = compute_s
    for cb in callbacks:
        cb.on_eval(trainer.step, metrics, files)
    checkpoint = trainer.save_checkpoint()
    for cb in callbacks:
        cb.on_checkpoint(trainer.step, checkpoint)
    return metrics, checkpoint


def fit(
    config: Config,
    callbacks: Sequence[Callback] = (),
    resume_from: str | Path | None = None,
    shared: SharedStore | None = None,
) -> FitResult:
    """Train CDM per ``config``; evaluate and checkpoint every ``train.eval_every`` steps and at the end.

    Args:
        config: the resolved configuration.
        callbacks: hooks receiving metrics, evaluation files and checkpoints.
        resume_from: a checkpoint directory written by an earlier run; training continues from its step.
        shared: a store of training views and evaluation sets computed once for many runs
            (:mod:`cdm.shared`); the run's numbers are the same with or without it.
    Raises:
        ValueError: bad data set or incompatible checkpoint (before any training).
        TrainingDiverged: the loss became NaN or infinite.
    """
    out_dir = Path(config.train.out_dir)
    for folder in ("checkpoints", "eval"):  # a link planted there is refused before the first step, not at a save
        check_within(out_dir / folder, out_dir, "train.out_dir")
    state = load_checkpoint(resume_from) if resume_from is not None else None
    trainer = Trainer(config, shared)
    if state is not None:
        trainer.restore(state, f"resume: {checkpoint_file(resume_from)}")
    record = run_record(config, trainer.train_set, trainer.val_set, trainer.device)
    for cb in callbacks:
        cb.on_start(record)
    if config.eval.only:  # PC²'s released weights scored as they are (model.init_from)
        return FitResult(trainer.step, *_evaluate_and_save(trainer, callbacks))
    return _train(trainer, callbacks)


def _train(trainer: Trainer, callbacks: Sequence[Callback]) -> FitResult:
    """The loop of :func:`fit`: steps until ``train.steps`` or ``train.compute_budget_s``, evaluating every
    ``train.eval_every`` steps, each ``train.eval_every_s`` seconds of compute, and at the end."""
    t_cfg = trainer.cfg.train
    metrics: dict[str, float] = {}
    checkpoint: Path | None = None
    sums = [0.0, 0.0, 0.0]
    window = skipped = 0
    clock = ComputeClock(trainer.device, trainer.compute_s)  # a resumed run goes on counting its budget
    start = time.perf_counter()
    window_start, cpu_start = start, time.process_time()
    every_s = t_cfg.eval_every_s
    next_eval_s = None if every_s is None else every_s * (math.floor(trainer.compute_s / every_s) + 1)
    while trainer.step < t_cfg.steps:
        losses = trainer.train_step(trainer.next_batch())
        sums = [s + v for s, v in zip(sums, losses[:3])]
        window += 1
        skipped += losses.skipped
        stop = any(cb.should_stop() for cb in callbacks)
        spent = trainer.agreed(clock.seconds()) if t_cfg.compute_budget_s or t_cfg.eval_every_s else 0.0
        last = trainer.step == t_cfg.steps or (t_cfg.compute_budget_s is not None and spent >= t_cfg.compute_budget_s)
        if trainer.step % t_cfg.log_every == 0 or last:
            now, cpu_now = time.perf_counter(), time.process_time()
            # This process's CPU time (all its threads) per step: what a step costs inside a sweep,
            # beside other trials, compared with benchmarks' isolated step (benchmarks/RESULTS.md).
            # train/skipped_steps counts this window's skipped steps (train.precision fp16, bf16).
            values = (sums[0] / window, sums[1] / window, sums[2] / window, trainer.optimiser.lr, float(skipped),
                      window / max(now - window_start, 1e-9), (cpu_now - cpu_start) / window, now - start)
            logged = dict(zip(TRAIN_METRICS, values, strict=True))
            for cb in callbacks:
                cb.on_step(trainer.step, logged)
            sums, window, skipped, window_start, cpu_start = [0.0, 0.0, 0.0], 0, 0, now, cpu_now
        if stop:
            break
        by_compute = next_eval_s is not None and spent >= next_eval_s
        if trainer.step % t_cfg.eval_every == 0 or last or by_compute:
            while next_eval_s is not None and spent >= next_eval_s:
                next_eval_s += t_cfg.eval_every_s
            with clock.paused():
                metrics, checkpoint = _evaluate_and_save(trainer, callbacks, clock.seconds())
            window_start, cpu_start = time.perf_counter(), time.process_time()  # steps/s measures training only
        if last:
            break
    return FitResult(trainer.step, metrics, checkpoint)
