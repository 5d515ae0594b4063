"""One optimiser step for every model this library trains (CDM and the BDM category prior).

PC²'s recipe: AdamW, linear warm-up then cosine decay to 0 (:func:`lr_factor`), gradients clipped
to a global norm of ``train.grad_clip`` before each step. In mixed precision (``train.precision``
fp16 or bf16, PC²'s Accelerate ``mixed_precision``) a step whose gradients hold inf or NaN is skipped,
optimiser and schedule alike, and fp16 scales the loss dynamically (``torch.amp.GradScaler``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import torch
from torch import Tensor, nn

from cdm.config import TrainConfig

__all__ = ["MAX_SKIPPED_IN_A_ROW", "Optimiser", "TrainingDiverged", "lr_factor"]

MAX_SKIPPED_IN_A_ROW = 32
"""Skipped steps in a row that end a mixed-precision run as diverged: fp16's scale has by then been
halved from 2¹⁶ to 2⁻¹⁶, past any overflow a scale can cure, and bf16 has no scale to lower."""


class TrainingDiverged(RuntimeError):
    """The loss became NaN or infinite; the message says at which step and which term."""


def lr_factor(step: int, warmup: int, total: int) -> float:
    """Factor of ``train.lr`` at ``step``: linear warm-up over ``warmup`` steps, then cosine decay to 0
    at ``total`` (PC²'s schedule)."""
    if step < warmup:
        return (step + 1) / warmup
    progress = (step - warmup) / max(1, total - warmup)
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


class Optimiser:
    """AdamW (``train.lr``, ``weight_decay``, ``betas``) on ``parameters`` with the warm-up + cosine
    schedule over ``train.steps`` and clipping at ``train.grad_clip``.

    ``optimizer``, ``scheduler`` and ``scaler`` are torch's, for checkpoints (their ``state_dict``).
    ``precision`` is the resolved ``train.precision`` (:func:`cdm.runtime.resolve_precision`): ``fp32``
    steps on every gradient, ``fp16`` scales the loss on ``device_type``'s ``GradScaler`` and with
    ``bf16`` skips non-finite steps (:meth:`step`).
    """

    def __init__(self, parameters: Iterable[nn.Parameter], cfg: TrainConfig, precision: str = "fp32",
                 device_type: str = "cpu"):
        self.parameters = list(parameters)
        self.grad_clip = cfg.grad_clip
        # fused: one kernel over all parameters. On one CPU thread it took 6–7 ms against 26–44 ms for
        # torch's per-tensor loop (70 tensors of the local model's sizes; the loop was ~10 % of a
        # quick-config step); it rounds differently from the loop, not otherwise.
        self.optimizer = torch.optim.AdamW(self.parameters, lr=cfg.lr, weight_decay=cfg.weight_decay, betas=cfg.betas,
                                           fused=True)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: lr_factor(s, cfg.warmup_steps, cfg.steps)
        )
        self.skips_nonfinite = precision != "fp32"
        # Disabled (fp32, bf16), the scaler is the identity: scale() returns the loss, step() steps.
        self.scaler = torch.amp.GradScaler(device_type, enabled=precision == "fp16")
        self.skipped = 0  # steps skipped for non-finite gradients by this process
        self.skipped_in_a_row = 0

    def step(self, loss: Tensor, reduce_gradients: Callable[[], None] | None = None) -> bool:
        """Back-propagate ``loss`` (times the fp16 loss scale), optionally reduce the gradients
        (data-parallel ranks), unscale, clip, step the optimiser and the schedule.

        Returns:
            False when mixed precision skipped the step: some gradient was inf or NaN (after
            unscaling); the weights, the optimiser's moments and the schedule are unchanged and fp16's
            scale is halved. Always True in fp32.
        """
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        if reduce_gradients is not None:
            reduce_gradients()
        self.scaler.unscale_(self.optimizer)
        # foreach: the per-tensor norms and rescales in two ops, not two per parameter (torch picks it
        # by itself on CUDA only); the same norms, summed in the same order.
        norm = torch.nn.utils.clip_grad_norm_(self.parameters, self.grad_clip, foreach=True)
        if self.skips_nonfinite and not torch.isfinite(norm):
            # The norm is inf/NaN exactly when a gradient is: the GradScaler's own found-inf test.
            if self.scaler.is_enabled():
                self.scaler.update()
            self.skipped += 1
            self.skipped_in_a_row += 1
            return False
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        self.skipped_in_a_row = 0
        return True

    @property
    def lr(self) -> float:
        """The learning rate the next step uses."""
        return self.scheduler.get_last_lr()[0]
