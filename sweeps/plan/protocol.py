"""The protocol card: every way a result's protocol differs from the paper's, said beside the number.

The card is a diff. :func:`protocol_card` compares every field of a trial's resolved config
(:meth:`cdm.config.Config.flat`) with the reference record of the spec's paper table on the data set
the trial reads (:func:`sweeps.plan.references.record`: the paper's, PC²'s or BDM's value of each field, with
its source) and adds what the config cannot say about the data on disk (a stand-in data set, BDM's
split file). Any field that differs from a stated value is a deviation; fields no source fixes are not,
though the card names the free choices that shape a result. Fields a spec sweeps (its grid, cells or
search space) are the table's own axes and are not compared. "Paper protocol, no deviations" only when
nothing differs. The card is printed by ``--dry-run``, shown in the results table, tagged on the parent MLflow
run (:data:`CARD_TAG`) and in the report.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from cdm.config import Config, config_field_paths
from cdm.registry import DATA_SETS as DATA_SETS_BY_KIND
from sweeps.plan.references import DATA_SETS, TABLES, Entry, Kind, NotStated, Stated, record, show

if TYPE_CHECKING:
    from sweeps.plan.trials import SweepPlan

__all__ = ["CARD_TAG", "NO_DEVIATIONS", "CardContext", "ProtocolCard", "plan_card", "protocol_card", "sweep_card"]

CARD_TAG = "protocol_card"
"""Tag of the parent MLflow run holding the card's lines, one per line."""

NO_DEVIATIONS = "Paper protocol, no deviations"
_PRIOR_SCALE = ("3D prior: each view's term is the mean over its pixels of the squared difference (Eq. 6's ‖·‖² "
                "sums them), a free choice that scales the term by 1/render_size²")


@dataclass(frozen=True)
class CardContext:
    """What the card needs beyond the trial's config: the spec's table, data sets, stand-in and axes."""

    datasets: tuple[Kind, ...] = DATA_SETS
    """The data sets the paper ran this table on (the spec's ``datasets:``)."""
    stand_in: str = ""
    """What the procedural data set stands in with (the spec's ``stand_in``)."""
    table: str | None = None
    """The spec's ``paper.table`` (a key of :data:`sweeps.plan.references.TABLES`); None: the paper's CDM."""
    swept: frozenset[str] = frozenset()
    """Dotted fields the spec sweeps: the table's axes, not compared."""


@dataclass(frozen=True)
class ProtocolCard:
    deviations: tuple[str, ...]
    """One line per deviation from the paper's protocol in force."""
    notes: tuple[str, ...] = ()
    """Free choices (no source fixes them), stated so a reader knows their origin."""

    @property
    def faithful(self) -> bool:
        return not self.deviations

    def lines(self) -> list[str]:
        head = [NO_DEVIATIONS] if self.faithful else [f"deviation: {d}" for d in self.deviations]
        return head + [f"note: {n}" for n in self.notes]

    def text(self) -> str:
        """One paragraph, e.g. for an MLflow tag or a table footer."""
        return "; ".join(self.lines())


def _reference(table: str | None, kinds: tuple[Kind, ...]) -> dict[str, Entry | None]:
    """The record of ``table`` on ``kinds``; on several (a stand-in for a table of two data sets), each field's
    entry where the records agree and None where they differ (the data set itself is then the deviation)."""
    records = [record(table, kind) for kind in kinds]
    first = records[0]
    return {path: entry if all(r.get(path) == entry for r in records[1:]) else None for path, entry in first.items()}


def _data_protocol(cfg: Config, ctx: CardContext) -> list[str]:
    """What the config cannot say about the data the trial reads: a stand-in, BDM's split file."""
    kind = cfg.data.kind
    if kind not in ctx.datasets:
        paper = " or ".join(DATA_SETS_BY_KIND[d].title for d in ctx.datasets)
        note = f"; {ctx.stand_in}" if ctx.stand_in and kind == "procedural" else ""
        return [f"data set: {DATA_SETS_BY_KIND[kind].title} stands in for {paper}{note}"]
    if kind == "shapenet_r2n2" and not (cfg.data.root and (Path(cfg.data.root) / "pc_dict_v2.json").is_file()):
        return ["split: PC15k's test folders, not BDM's R2N2 test split (put BDM's pc_dict_v2.json in data.root)"]
    return []


class _Diff(NamedTuple):
    """One trial's comparison with its record, in config-field order."""

    deviations: list[str]
    free: list[str]
    """``path = value`` of each noted free choice in force."""
    prior_3d: bool
    unreviewed: list[str]
    """Config fields without an entry in the record."""


def _diff(cfg: Config, ctx: CardContext) -> _Diff:
    """Compare every field of ``cfg`` with the record, then list what the record states that the config cannot hold.

    A stated field the config does not have (yet) is a deviation: this code cannot be set to the reference
    (e.g. ``model.denoiser`` before PC²'s PVCNN2 is selectable). A condition on a missing field does not hold.
    """
    flat = cfg.flat()
    kinds = (cfg.data.kind,) if cfg.data.kind in ctx.datasets else ctx.datasets
    reference = _reference(ctx.table, kinds)
    deviations = _data_protocol(cfg, ctx)
    free: list[str] = []
    unreviewed: list[str] = []
    for path, value in flat.items():
        if path in ctx.swept or path == "data.kind":  # data.kind: the data-set line of _data_protocol
            continue
        if path not in reference:
            unreviewed.append(path)
            continue
        entry = reference[path]
        if isinstance(entry, Stated) and entry.applies(flat) and not entry.holds(value):
            deviations.append(f"{path}: {show(value)}, not {entry.shown} ({entry.source})")
        elif isinstance(entry, NotStated) and entry.noted and entry.applies(flat):
            free.append(f"{path} = {show(value)}")
    for path, entry in reference.items():
        if path not in flat and path not in ctx.swept and isinstance(entry, Stated) and entry.applies(flat):
            deviations.append(f"{path}: not a field of this config, so not {entry.shown} ({entry.source})")
    return _Diff(deviations, free, cfg.priors.prior_3d, unreviewed)


def sweep_card(configs: Iterable[Config], datasets: Iterable[Kind] = (), stand_in: str = "", table: str | None = None,
               swept: Iterable[str] = ()) -> ProtocolCard:
    """The cards of a sweep's cells merged: each deviation and free choice once, in config-field order.

    Args:
        configs: every cell's resolved config.
        datasets: the data sets the table ran on (the spec's ``datasets:``; empty: both).
        stand_in: what the procedural data set stands in with (the spec's ``stand_in``).
        table: the spec's ``paper.table``; None compares with the paper's CDM.
        swept: the fields the spec sweeps, not compared.
    """
    ctx = CardContext(tuple(datasets) or DATA_SETS, stand_in, table, frozenset(swept))
    diffs = [_diff(cfg, ctx) for cfg in configs]
    order = {path: i for i, path in enumerate(config_field_paths())}
    record_paths = {path for kind in ctx.datasets for path in record(table, kind)}

    def rank(line: str) -> int:  # data-protocol lines first, then config fields, then fields the config lacks
        head = line.split(":")[0].split(" = ")[0]
        return order[head] if head in order else len(order) if head in record_paths else -1

    def merged(lines: Iterable[str]) -> list[str]:
        return sorted(dict.fromkeys(lines), key=rank)

    notes = [_PRIOR_SCALE] if any(d.prior_3d for d in diffs) else []
    if free := merged(line for d in diffs for line in d.free):
        notes.append("free choices (no source states them): " + ", ".join(free))
    if unreviewed := list(dict.fromkeys(path for d in diffs for path in d.unreviewed)):
        notes.append("not compared (no entry in sweeps/plan/references.py): " + ", ".join(unreviewed))
    return ProtocolCard(tuple(merged(line for d in diffs for line in d.deviations)), tuple(notes))


def protocol_card(cfg: Config, ctx: CardContext = CardContext()) -> ProtocolCard:
    """The card of one trial's resolved config: its data protocol, then every field that differs from the record."""
    return sweep_card([cfg], ctx.datasets, ctx.stand_in, ctx.table, ctx.swept)


def plan_card(plan: SweepPlan) -> ProtocolCard:
    """The card of a sweep plan: its cells' configs (an Optuna plan: the fixed settings and ``--set``).

    A table without a record is compared with the paper's CDM and the card says so.
    """
    spec = plan.spec
    table = spec.paper.table if spec.paper else None
    card = sweep_card(plan.configs, spec.datasets, spec.stand_in, table if table in TABLES else None, plan.swept)
    if table is None or table in TABLES:
        return card
    return ProtocolCard(card.deviations, (*card.notes, f"{table}: no reference record; compared with the paper's CDM"))
