"""One optimiser step for every model this library trains (CDM and the BDM category prior).

PC²'s recipe: AdamW, linear warm-up then cosine decay to 0 (:func:`lr_factor`), gradients clipped
to a global norm of ``train.grad_clip`` before each step. In mixed precision (``train.precision``
fp16 or bf16, PC²'s Accelerate ``mixed_precision``) a step whose gradients hold inf or NaN is skipped,
optimiser and schedule alike, and fp16 scales the loss dynamically (``torch.amp.GradScaler``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch import Tensor, nn

from cdm.config import TrainConfig

__all__ = ["MAX_SKIPPED_IN_A_ROW", "Optimiser", "TrainingDiverged", "check_like", "lr_factor"]

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

    def restore(self, optimizer: Any, scheduler: Any, label: str) -> None:
        """Continue from a checkpoint's ``optimizer`` and ``scheduler`` dicts, each checked first against this
        optimiser's own (:func:`check_like`), and per parameter AdamW's step and moments against the
        parameter's shape and dtype, the second moments ≥ 0. torch's ``load_state_dict`` checks neither:
        it takes moments of another shape (a step then broadcasts them or fails part way) and LambdaLR's
        copies every key of the dict into the scheduler's attributes.

        Raises:
            ValueError: ``label``, then the first entry that differs and what this run expects.
        """
        if not isinstance(optimizer, dict) or "state" not in optimizer:
            raise ValueError(f"{label}: its optimizer is {_kind(optimizer)}, not an optimizer's state dict")
        own = self.optimizer.state_dict()
        check_like({k: v for k, v in optimizer.items() if k != "state"}, {k: v for k, v in own.items() if k != "state"},
                   f"{label}: its optimizer")
        if type(optimizer["state"]) is not dict or not set(optimizer["state"]) <= set(range(len(self.parameters))):
            raise ValueError(f"{label}: its optimizer's state is not keyed by this run's "
                             f"{len(self.parameters)} parameter indices")
        for index, moments in optimizer["state"].items():
            p = self.parameters[index]
            like = {"step": torch.empty((), dtype=torch.float32, device="meta"),
                    "exp_avg": torch.empty_like(p, device="meta"), "exp_avg_sq": torch.empty_like(p, device="meta")}
            check_like(moments, like, f"{label}: its optimizer's state[{index}]")
            if (moments["exp_avg_sq"] < 0).any():
                raise ValueError(f"{label}: its optimizer's state[{index}]['exp_avg_sq'] holds a negative second "
                                 "moment")
        check_like(scheduler, self.scheduler.state_dict(), f"{label}: its scheduler")
        self.optimizer.load_state_dict(optimizer)
        self.scheduler.load_state_dict(scheduler)

    @property
    def lr(self) -> float:
        """The learning rate the next step uses."""
        return self.scheduler.get_last_lr()[0]


def check_like(value: Any, reference: Any, where: str) -> None:
    """Refuse ``value`` unless it has ``reference``'s layout: dicts with the same keys, lists and tuples of
    the same length, tensors of the same dtype and shape and finite, floats finite and ≥ 0, ints ≥ 0
    (counters), and every other value (flags, ``None``, parameter indices) equal to the reference's.

    Raises:
        ValueError: ``where``, then the path to the first entry that differs and what was expected.
    """
    stack = [(value, reference, "")]
    while stack:
        value, reference, path = stack.pop()
        problem = _difference(value, reference, path)
        if problem:
            raise ValueError(f"{where}{path} {problem}")
        if isinstance(reference, dict):
            stack += [(value[key], reference[key], f"{path}[{key!r}]") for key in reference]
        elif isinstance(reference, (list, tuple)) and not path.endswith("['params']"):
            stack += [(v, r, f"{path}[{i}]") for i, (v, r) in enumerate(zip(value, reference))]


def _difference(value: Any, reference: Any, path: str) -> str:
    """What is wrong with ``value`` where ``reference`` stands (one level deep), or ``""``."""
    if isinstance(reference, dict):
        if not isinstance(value, dict) or set(value) != set(reference):
            keys = sorted(map(str, value)) if isinstance(value, dict) else type(value).__name__
            return f"is {keys}, not a dict of {sorted(map(str, reference))}"
    elif isinstance(reference, (list, tuple)):
        if type(value) is not type(reference) or len(value) != len(reference):
            return f"is {_kind(value)}, not a {type(reference).__name__} of {len(reference)}"
        if path.endswith("['params']") and value != reference:
            return f"is {value[:8]}, not this run's parameter indices"
    elif isinstance(reference, Tensor):
        if not isinstance(value, Tensor) or value.dtype != reference.dtype or value.shape != reference.shape:
            return f"is {_kind(value)}, not a {reference.dtype} tensor of shape {tuple(reference.shape)}"
        if not torch.isfinite(value).all():
            return "holds inf or NaN"
    elif type(reference) is float:
        if type(value) is not float or not math.isfinite(value) or value < 0:
            return f"is {_kind(value)}, not a finite float ≥ 0"
    elif type(reference) is int:
        if type(value) is not int or value < 0:
            return f"is {_kind(value)}, not an int ≥ 0"
    elif type(value) is not type(reference) or value != reference:
        return f"is {_kind(value)}; this run's is {reference!r}"
    return ""


def _kind(value: Any) -> str:
    if isinstance(value, Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    if isinstance(value, (list, tuple)):
        return f"a {type(value).__name__} of {len(value)}"
    text = repr(value) if isinstance(value, (int, float, str, type(None))) else f"a {type(value).__name__}"
    return text if len(text) <= 40 else f"{text[:37]}..."
