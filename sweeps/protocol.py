"""The protocol card: every way a result's protocol differs from the paper's, said beside the number.

A number from this platform reads as comparable with the paper's only when data set, scoring and
sampler are the references' (PC², lukemelas/projection-conditioned-point-cloud-diffusion; BDM,
mlpc-ucsd/BDM). :func:`protocol_card` runs :data:`CHECKS` — small functions, one per aspect, each
returning the deviation it finds in one trial's config or None — and :func:`sweep_card` merges the
cards of a sweep's cells. The card is printed by ``--dry-run``, shown in the results table, tagged on
the parent MLflow run and in the report. "Paper protocol, no deviations" only when no check finds one.

What the paper's protocol is, per data set (the references' defaults):

- ShapeNet (BDM): R2N2 renderings + PC15k in the v1 frame, R2N2 ``test`` split (BDM's
  ``pc_dict_v2.json``), every object, 4,096 points, BDM's global normalisation (``eval.normalise:
  reference``); Co3D (PC²): ``fewview_dev`` ``val``, every sequence, 16,384 points, world units.
- Both: 224² images, ε-prediction, PC²'s linear β 1e-5 → 8e-3 over 1,000 steps, sampled with DDPM over
  all 1,000 steps without clipping (PC²'s ``experiments/config/structured.py``), 100k training steps
  at batch 8, a frozen ViT-S/16 encoder; the 2D depth prior from an estimator, not ground truth.
- λ (the 3D prior's weight): the paper gives no value, so every λ is ours; the card notes it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cdm.config import Config, load_config

if TYPE_CHECKING:
    from sweeps.plan import SweepPlan

__all__ = ["CARD_TAG", "CHECKS", "NO_DEVIATIONS", "CardContext", "ProtocolCard", "plan_card", "protocol_card", "sweep_card"]

CARD_TAG = "protocol_card"
"""Tag of the parent MLflow run holding the card's lines, one per line."""

NO_DEVIATIONS = "Paper protocol, no deviations"
REFERENCE_KINDS = ("shapenet_r2n2", "co3d")
_NAMES = {"shapenet_r2n2": "ShapeNet-R2N2 + PC15k", "co3d": "Co3D v2", "procedural": "the procedural data set",
          "meshes": "a mesh folder"}
_EVAL_SPLIT = {"shapenet_r2n2": "test", "co3d": "val"}
_POINTS = {"shapenet_r2n2": 4096, "co3d": 16384}
"""Points per cloud the references train and score on: BDM 4,096 (``experiments/example_sample.sh``), PC² 16,384."""


@dataclass(frozen=True)
class CardContext:
    """What a check needs beyond the trial's config: the spec's data sets and stand-in note."""

    datasets: tuple[str, ...] = REFERENCE_KINDS
    stand_in: str = ""


Check = Callable[[Config, CardContext], str | None]


def _data_set(cfg: Config, ctx: CardContext) -> str | None:
    if cfg.data.kind in ctx.datasets:
        return None
    paper = " or ".join(_NAMES[d] for d in ctx.datasets)
    note = f"; {ctx.stand_in}" if ctx.stand_in and cfg.data.kind == "procedural" else ""
    return f"data set: {_NAMES[cfg.data.kind]} stands in for {paper}{note}"


def _split(cfg: Config, ctx: CardContext) -> str | None:
    kind = cfg.data.kind
    if kind not in REFERENCE_KINDS:
        return None
    if cfg.data.eval_split != _EVAL_SPLIT[kind]:
        return f"split: {cfg.data.eval_split} held out (the reference scores {_EVAL_SPLIT[kind]})"
    if kind == "shapenet_r2n2" and not (cfg.data.root and (Path(cfg.data.root) / "pc_dict_v2.json").is_file()):
        return "split: PC15k's test folders, not BDM's R2N2 test split (put BDM's pc_dict_v2.json in data.root)"
    return None


def _objects(cfg: Config, ctx: CardContext) -> str | None:
    if cfg.eval.protocol == "paper":
        return None
    return f"objects: the first {cfg.eval.num_objects} held-out objects per category (the references score all)"


def _normalisation(cfg: Config, ctx: CardContext) -> str | None:
    if cfg.eval.normalise == "reference" and cfg.data.kind in REFERENCE_KINDS:
        return None
    return "normalisation: per-shape bounding box to [-1, 1]³ (BDM: global mean/σ on ShapeNet; PC²: Co3D world units)"


def _points(cfg: Config, ctx: CardContext) -> str | None:
    want = _POINTS.get(cfg.data.kind, 4096)
    have = {cfg.data.num_points, cfg.eval.num_points}
    if have == {want}:
        return None
    return f"points: {cfg.data.num_points} per cloud, {cfg.eval.num_points} scored (the reference: {want})"


def _metric(cfg: Config, ctx: CardContext) -> str | None:
    if cfg.eval.f1_threshold == 0.01:
        return None
    return f"metric: F1 at τ = {cfg.eval.f1_threshold:g} on the squared distance (BDM: 0.01)"


def _sampler(cfg: Config, ctx: CardContext) -> str | None:
    d = cfg.diffusion
    if d.sampler == "ddpm" and d.clip_x0 is None:
        return None
    how = (f"DDIM over {d.sample_steps} steps, {d.timestep_spacing} spacing" if d.sampler == "ddim"
           else f"DDPM over {d.num_steps} steps")
    clip = f", x̂₀ clipped to ±{d.clip_x0:g}" if d.clip_x0 is not None else ""
    return f"sampler: {how}{clip} (PC²: DDPM over 1,000 steps, unclipped)"


def _diffusion(cfg: Config, ctx: CardContext) -> str | None:
    d = cfg.diffusion
    out = []
    if d.prediction != "eps":
        out.append(f"{d.prediction}-prediction (paper: ε)")
    if (d.num_steps, d.beta_start, d.beta_end) != (1000, 1e-5, 8e-3):
        out.append(f"β {d.beta_start:g} → {d.beta_end:g} over {d.num_steps} steps (PC²: 1e-5 → 8e-3 over 1,000)")
    return "diffusion: " + "; ".join(out) if out else None


def _training(cfg: Config, ctx: CardContext) -> str | None:
    t, out = cfg.train, []
    if t.steps != 100_000:
        out.append(f"{t.steps:,} steps (PC²: 100,000)")
    if t.batch_size != 8:
        out.append(f"batch {t.batch_size} (paper: 8)")
    if cfg.data.image_size != 224:
        out.append(f"{cfg.data.image_size}² images (paper: 224²)")
    if (t.lr, tuple(t.betas), t.warmup_steps) != (1e-3, (0.95, 0.999), 2000):
        out.append(f"AdamW lr {t.lr:g}, betas ({t.betas[0]:g}, {t.betas[1]:g}), {t.warmup_steps:,} warm-up steps "
                   "(PC²: 1e-3, (0.95, 0.999), 2,000)")
    return "training: " + ", ".join(out) if out else None


def _depth_renders(cfg: Config, ctx: CardContext) -> str | None:
    p = cfg.priors
    if not p.prior_3d or p.render_kind != "depth" or p.depth_layer is not None:
        return None
    return "3D prior: depth renders average front and back surfaces (the paper's PyTorch3D z-buffer keeps the nearest)"


def _encoder(cfg: Config, ctx: CardContext) -> str | None:
    if cfg.model.encoder == "vit_s16":  # its weights are required (model.encoder_weights) and checked by hash
        return None
    return "encoder: a small CNN trained from scratch (PC²: frozen ViT-S/16, 384 channels)"


def _depth_source(cfg: Config, ctx: CardContext) -> str | None:
    # Estimated maps (priors.depth_source: maps) are the paper's route, whatever estimator made them.
    if cfg.priors.prior_2d != "depth" or cfg.priors.depth_source == "maps":
        return None
    return "depth: the 2D depth prior reads ground-truth depth maps, an upper bound (the paper estimates depth)"


CHECKS: list[Check] = [_data_set, _split, _objects, _normalisation, _points, _metric, _sampler, _diffusion,
                       _training, _depth_renders, _encoder, _depth_source]
"""The card's checks, in the order the card lists them; append a function to check one more aspect."""


@dataclass(frozen=True)
class ProtocolCard:
    deviations: tuple[str, ...]
    """One line per deviation from the paper's protocol in force."""
    notes: tuple[str, ...] = ()
    """Choices the paper leaves open (λ), stated so a reader knows their origin."""

    @property
    def faithful(self) -> bool:
        return not self.deviations

    def lines(self) -> list[str]:
        head = [NO_DEVIATIONS] if self.faithful else [f"deviation: {d}" for d in self.deviations]
        return head + [f"note: {n}" for n in self.notes]

    def text(self) -> str:
        """One paragraph, e.g. for an MLflow tag or a table footer."""
        return "; ".join(self.lines())


def _notes(cfg: Config) -> list[str]:
    if not cfg.priors.prior_3d:
        return []
    return [f"λ = {cfg.priors.lambda_3d:g} is ours: the paper gives no value for the 3D prior's weight"]


def protocol_card(cfg: Config, ctx: CardContext = CardContext()) -> ProtocolCard:
    """The card of one trial's resolved config."""
    return ProtocolCard(tuple(d for check in CHECKS if (d := check(cfg, ctx)) is not None), tuple(_notes(cfg)))


def sweep_card(configs: Iterable[Config], datasets: Iterable[str] = (), stand_in: str = "") -> ProtocolCard:
    """The cards of a sweep's cells merged: each deviation and note once, in check order."""
    ctx = CardContext(tuple(datasets) or REFERENCE_KINDS, stand_in)
    deviations: dict[str, None] = {}
    notes: dict[str, None] = {}
    for cfg in configs:
        card = protocol_card(cfg, ctx)
        deviations.update(dict.fromkeys(card.deviations))
        notes.update(dict.fromkeys(card.notes))
    return ProtocolCard(tuple(deviations), tuple(notes))


def plan_card(plan: SweepPlan) -> ProtocolCard:
    """The card of a sweep plan: its cells' configs (an Optuna plan: the fixed settings and ``--set``)."""
    configs = [c.config for c in plan.cells] or [load_config(None, {**plan.fixed, **plan.sets})]
    return sweep_card(configs, plan.spec.datasets, plan.spec.stand_in)
