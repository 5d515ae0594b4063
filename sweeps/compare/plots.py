"""Plots of a sweep for comparing its cells: metric vs swept value, training curves, Optuna's own views.

Knows nothing of MLflow: :mod:`sweeps.results.publish` reads the runs and hands in plain numbers. Every
function writes one PNG (matplotlib's Agg backend, no display needed) and returns its path.
"""

from __future__ import annotations

import io
import math
import statistics
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from cdm.io.meshes import read_vertices
from cdm.metric_names import COMPUTE_METRIC, METRICS, object_column
from cdm.metric_names import label as metric_label
from cdm.metric_names import mode as metric_mode
from sweeps.compare.rules import baseline_key, baseline_name, headline
from sweeps.compare.table import COST_COLUMN
from sweeps.store.files import write_file

__all__ = ["DPI", "PlotPoint", "has_curve", "log_spaced", "metric_vs_value", "optuna_plots", "read_ply", "save_figure",
           "training_curves", "view_cloud"]

DPI = 150
"""Resolution of every saved figure."""

FONT = 9
"""Smallest text in a figure (points): legible when a paper prints the figure a column wide."""


@dataclass(frozen=True)
class PlotPoint:
    """One finished trial as the plots see it."""

    cell: str
    values: dict[str, Any]
    """Swept config values of the trial (dotted key → value)."""
    metrics: dict[str, float]
    paper: dict[str, float] = field(default_factory=dict)
    """The paper's numbers for this cell, by metric name (``eval/f1``, ``eval/f1/teddybear``)."""
    paper_label: str | None = None
    """The paper's table row those numbers come from (``10 frames + 0.04 point size``)."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _axis(points: Sequence[PlotPoint]) -> tuple[list[str], dict[str, float], str | None]:
    """Cells in plotting order, their x position, and the x label: the value itself when one numeric
    field is swept (so spacing means something), else the cell's index with its name as tick label."""
    cells = list(dict.fromkeys(p.cell for p in points))
    keys = list(dict.fromkeys(k for p in points for k in p.values))
    first = {p.cell: p.values for p in reversed(points)}
    numeric = len(keys) == 1 and all(
        isinstance(first[c].get(keys[0]), (int, float)) and not isinstance(first[c].get(keys[0]), bool) for c in cells
    )
    if numeric:
        x = {c: float(first[c][keys[0]]) for c in cells}
        return sorted(cells, key=x.__getitem__), x, keys[0]  # left to right, whatever order the trials came in
    return cells, {c: float(i) for i, c in enumerate(cells)}, None


def log_spaced(values: Sequence[float]) -> bool:
    """Whether a grid of swept values reads better on a log axis: all positive, spanning at least 4×,
    and more evenly spaced in log than in linear terms (0.0075, 0.01, 0.02, 0.04, 0.08: yes; 1, 2, 3, 4: no)."""
    xs = sorted(set(values))
    if len(xs) < 3 or xs[0] <= 0 or xs[-1] / xs[0] < 4:
        return False

    def unevenness(steps: np.ndarray) -> float:
        return float(np.std(steps) / np.mean(steps))

    return unevenness(np.diff(np.log(xs))) < unevenness(np.diff(xs))


def metric_vs_value(points: Sequence[PlotPoint], metric: str, title: str, path: Path, paper_table: str = "paper",
                    intervals: Mapping[str, tuple[float, float]] | None = None, *,
                    f1_thresholds: float | Sequence[float]) -> Path:
    """``metric`` (and its CD/F1 partner) against the swept value: mean per cell, one line for all objects
    and one per category; bars: the cell's 95 % paired interval against the reference cell
    (``intervals``: cell → Δ interval ``(low, high)`` of ``metric``, drawn around the cell's mean by its
    distance to Δ's bounds), else ± std over seeds; the baselines (``baseline/<name>/…`` in the points'
    metrics) as dashed horizontal lines; the paper's numbers as stars, each labelled with its
    ``paper_table`` row. Legends sit below the axes, outside the data; a log axis says so. F1's axis names the
    trials' ``f1_thresholds`` (their ``eval.f1_threshold``)."""
    plt = _pyplot()
    shown = headline(metric)
    cells, x, xlabel = _axis(points)
    categories = sorted({k.rsplit("/", 1)[1] for p in points for k in p.metrics if k.startswith(metric + "/")})
    baselines = sorted({k.split("/")[1] for p in points for k in p.metrics if k.startswith("baseline/")})
    fig, axes = plt.subplots(1, len(shown), figsize=(6.5 * len(shown), 5.5), squeeze=False)
    for ax, m in zip(axes[0], shown):
        for i, series in enumerate(["all", *categories]):
            key = m if series == "all" else f"{m}/{series}"
            colour = f"C{i}"
            xs, means, bars = _cell_means(points, cells, x, key, intervals if key == metric else None)
            if xs:
                label = f"ours: {'all objects' if series == 'all' else series}"
                if series == "all" and m == metric and intervals:
                    label += " (bars: 95% paired interval vs the reference cell)"
                ax.errorbar(xs, means, yerr=np.array(bars).T, fmt="o-", color=colour, capsize=4,
                            lw=2 if series == "all" else 1, label=label)
            _paper_stars(ax, points, x, key, colour, paper_table)
        _baseline_lines(ax, points, baselines, m)
        _value_axes(ax, m, cells, x, xlabel, f1_thresholds)
    fig.suptitle(title, fontsize=FONT + 2)
    fig.tight_layout()
    return _save(fig, path)


def _cell_means(
    points: Sequence[PlotPoint],
    cells: list[str],
    x: Mapping[str, float],
    key: str,
    intervals: Mapping[str, tuple[float, float]] | None,
) -> tuple[list[float], list[float], list[tuple[float, float]]]:
    """Per cell with a finite ``key``: its x, its mean over seeds and its bar (down, up): half the paired
    interval's width where ``intervals`` has the cell, else ± std over seeds."""
    xs, means, bars = [], [], []
    for c in cells:
        values = [p.metrics[key] for p in points if p.cell == c and key in p.metrics and math.isfinite(p.metrics[key])]
        if values:
            xs.append(x[c])
            means.append(statistics.fmean(values))
            spread = statistics.stdev(values) if len(values) > 1 else 0.0
            # The paired interval is Δ's: drawn around the mean as its half-width.
            paired = (intervals or {}).get(c)
            bars.append(((paired[1] - paired[0]) / 2,) * 2 if paired else (spread, spread))
    return xs, means, bars


def _paper_stars(ax, points: Sequence[PlotPoint], x: Mapping[str, float], key: str, colour: str,
                 paper_table: str) -> None:
    """The paper's numbers for ``key`` as stars, each labelled with its paper row (else its cell)."""
    paper = {p.cell: (p.paper[key], p.paper_label) for p in points if key in p.paper}
    if not paper:
        return
    ax.scatter([x[c] for c in paper], [v for v, _ in paper.values()], marker="*", s=160, color=colour,
               edgecolor="black", zorder=3, label=f"{paper_table} (the paper's data set, not ours)")
    for c, (value, row) in paper.items():
        ax.annotate(row or c, (x[c], value), textcoords="offset points", xytext=(6, 4), fontsize=FONT, color=colour)


def _baseline_lines(ax, points: Sequence[PlotPoint], baselines: list[str], metric: str) -> None:
    """Each baseline's mean on ``metric`` as a dashed horizontal line, labelled."""
    for i, b in enumerate(baselines):
        if values := [p.metrics[baseline_key(b, metric)] for p in points if baseline_key(b, metric) in p.metrics]:
            ax.axhline(statistics.fmean(values), color="0.45", lw=1, ls=(0, (4, 2 + 2 * i)), zorder=1)
            # Labels staggered along the line: baselines often score alike (category mean, retrieval).
            ax.annotate(f"baseline: {baseline_name(b)}", (1.0 - 0.3 * i, statistics.fmean(values)),
                        xycoords=("axes fraction", "data"), xytext=(-2, 2), textcoords="offset points", ha="right",
                        va="bottom", fontsize=FONT, color="0.35")


def _value_axes(ax, m: str, cells: list[str], x: Mapping[str, float], xlabel: str | None,
                f1_thresholds: float | Sequence[float]) -> None:
    """The swept value on x (cell names, or numbers on a log axis when log-spaced), ``m`` on y (F1 labelled at
    ``f1_thresholds``), the legend below the axes."""
    if xlabel is None:
        ax.set_xticks([x[c] for c in cells], cells, rotation=20, ha="right", fontsize=FONT)
    else:
        ax.set_xlabel(xlabel, fontsize=FONT + 1)
        if log_spaced(list(x.values())):
            ax.set_xscale("log")
            ax.set_xlabel(f"{xlabel} (log scale)", fontsize=FONT + 1)
            ax.minorticks_off()
        ax.set_xticks(sorted(x.values()), [f"{v:g}" for v in sorted(x.values())])
    better = "lower" if (where := object_column(m)) and METRICS[where[0]].mode == "min" else "higher"
    ax.set_ylabel(f"{metric_label(m, f1_thresholds)}, {better} is better", fontsize=FONT + 1)
    ax.tick_params(labelsize=FONT)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=FONT, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)


def has_curve(history: Mapping[str, Sequence[tuple[int, float]]], metric: str) -> bool:
    """Whether a trial's history draws a line in :func:`training_curves`: a logged training loss, or two
    evaluations of ``metric`` (a trial that only scored its starting weights, ``eval.only``, has neither)."""
    return bool(history.get("train/loss")) or len(history.get(metric, ())) >= 2


_TERMS = ("diffusion term", "λ × 3D prior term", "total (Eq. 6)")
"""The panels of the loss in :func:`training_curves`, in order."""


def _loss_terms(history: Mapping[str, Sequence[tuple[int, float]]], metric: str) -> dict[str, list[tuple[int, float]]]:
    """A trial's loss as its :data:`_TERMS` (the prior term is ``train/loss − train/loss_diffusion``, Eq. 6) and
    its ``metric`` evaluations, each as ``(step, value)`` pairs in step order."""
    total, diffusion = sorted(history.get("train/loss", ())), dict(history.get("train/loss_diffusion", ()))
    out = {_TERMS[0]: [(s, diffusion[s]) for s, _ in total if s in diffusion],
           _TERMS[1]: [(s, v - diffusion[s]) for s, v in total if s in diffusion], _TERMS[2]: total}
    return out | ({metric: sorted(history[metric])} if history.get(metric) else {})


def training_curves(
    curves: Mapping[str, Mapping[str, Sequence[tuple[int, float]]]],
    cells: Mapping[str, str],
    metric: str,
    title: str,
    path: Path,
    *,
    f1_thresholds: float | Sequence[float],
) -> Path:
    """The loss against the training step, its terms apart (:func:`_loss_terms`), one line per trial, one colour
    per cell (its seeds share it). The prior term grows with λ and the point size, so only the diffusion term
    compares learning across such cells. ``metric`` gets a panel of its evaluations (markers, joined when
    a trial evaluated more than once).

    Args:
        curves: trial label → metric name (``train/loss``, ``train/loss_diffusion``, ``metric``) →
            ``(step, value)`` pairs (any order).
        cells: trial label → cell name.
        f1_thresholds: the trials' ``eval.f1_threshold``, which F1's axis names.
    """
    plt = _pyplot()
    panels = {label: _loss_terms(history, metric) for label, history in curves.items()}
    keys = [k for k in (*_TERMS, metric) if any(p.get(k) for p in panels.values())]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.8 * len(keys), 3.6), squeeze=False)
    colours = {c: f"C{i % 10}" for i, c in enumerate(dict.fromkeys(cells[label] for label in curves))}
    labelled: set[str] = set()
    for label, lines in panels.items():
        cell = cells[label]
        for ax, key in zip(axes[0], keys):
            if lines.get(key):
                ax.plot(*zip(*lines[key]), "o-" if key == metric else "-", color=colours[cell],
                        label=None if cell in labelled else cell)
        labelled.add(cell)
    for ax, key in zip(axes[0], keys):
        ax.set_xlabel("training step", fontsize=FONT)
        ax.set_ylabel(metric_label(key, f1_thresholds) + " at evaluations" if key == metric else "loss (Eq. 6)",
                      fontsize=FONT)
        ax.set_title(key, fontsize=FONT + 1)
        ax.tick_params(labelsize=FONT)
        ax.grid(alpha=0.3)
    if 1 < len(colours) <= 12:  # one cell needs no legend; beyond 12 a legend hides the curves
        fig.legend(*axes[0][0].get_legend_handles_labels(), fontsize=FONT, loc="upper center",
                   ncol=min(len(colours), 6), bbox_to_anchor=(0.5, 0.0), frameon=False)
    fig.suptitle(title, fontsize=FONT + 2)
    fig.tight_layout()
    return _save(fig, path)


def optuna_plots(
    trials: Sequence[tuple[dict[str, Any], Mapping[str, float] | None]],
    distributions: Mapping[str, Any],
    mode: Literal["min", "max"],
    metric: str,
    folder: Path,
) -> list[Path]:
    """Optuna's optimisation history, parameter importances and Pareto front for a search rebuilt from its trials.

    Args:
        trials: per trial, the sampled values and its last evaluation's metrics (None: failed, not counted).
        distributions: ``optuna.distributions`` of the search space, by config key.
    Returns:
        ``optuna_history.png``; ``optuna_importance.png`` when two or more trials finished (importances need a
        spread of finished trials); ``optuna_pareto.png`` when two or more trials report ``metric``, its partner
        and :data:`~cdm.metric_names.COMPUTE_METRIC`: the trials no other beats on all three at once.
    """
    import optuna
    from optuna.visualization import matplotlib as ovm

    plt = _pyplot()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    objectives = [*headline(metric), COMPUTE_METRIC]
    directions = {m: "minimize" if (mode if m == metric else _mode(m)) == "min" else "maximize" for m in objectives}
    single = _study(optuna, [directions[metric]], [(v, [m[metric]] if m and metric in m else None) for v, m in trials],
                    distributions)
    scored = [(v, [m[k] for k in objectives]) for v, m in trials if m and all(k in m for k in objectives)]
    paths = []
    # Optuna's plots switch the global style to ggplot; the context restores it for every later figure.
    # Its matplotlib backend is marked experimental, which would warn on every sweep.
    with plt.rc_context(), warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        ax = ovm.plot_optimization_history(single, target_name=metric)
        paths.append(_save(ax.figure, folder / "optuna_history.png"))
        if sum(m is not None and metric in m for _, m in trials) >= 2:
            ax = ovm.plot_param_importances(single, target_name=metric)
            paths.append(_save(ax.figure, folder / "optuna_importance.png"))
        if len(objectives) == 3 and len(scored) >= 2:
            front = _study(optuna, [directions[m] for m in objectives], scored, distributions)
            ax = ovm.plot_pareto_front(front, target_names=[_short(m) for m in objectives])
            paths.append(_save(ax.figure, folder / "optuna_pareto.png"))
    return paths


def _study(optuna, directions: list[str], trials: Sequence[tuple[dict[str, Any], list[float] | None]],
           distributions: Mapping[str, Any]):
    """An in-memory Optuna study holding ``trials`` (values, objective values; None: failed)."""
    study = optuna.create_study(directions=directions)
    for values, scores in trials:
        state = optuna.trial.TrialState.COMPLETE if scores is not None else optuna.trial.TrialState.FAIL
        study.add_trial(optuna.trial.create_trial(params=values, distributions=dict(distributions), values=scores,
                                                  state=state))
    return study


def _mode(metric: str) -> Literal["min", "max"]:
    """Which way ``metric`` is better: a declared evaluation metric's own direction, compute always less."""
    return "min" if metric == COMPUTE_METRIC else metric_mode(metric)


def _short(metric: str) -> str:
    """An axis name: ``eval/f1`` → ``f1``, the compute metric with its unit."""
    return COST_COLUMN if metric == COMPUTE_METRIC else metric.removeprefix("eval/")


def read_ply(path: Path) -> np.ndarray:
    """The ``(N, 3)`` points of an ASCII PLY as written by :func:`cdm.evaluate.write_ply`."""
    return read_vertices(Path(path), "reconstruction").astype(np.float32)


def view_cloud(points: np.ndarray, elevation: float = 20.0, azimuth: float = 30.0, title: str = ""):
    """A 3D scatter of an ``(N, 3)`` cloud seen from ``elevation``/``azimuth`` degrees; returns the figure.

    The notebook turns it with sliders. Axes follow the data's frame (PyTorch3D world: +Y up), so the
    cloud is drawn with Y as matplotlib's vertical axis.
    """
    plt = _pyplot()
    fig = plt.figure(figsize=(4.5, 4.5))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(points[:, 0], points[:, 2], points[:, 1], s=2, c=points[:, 1], cmap="viridis")
    ax.view_init(elev=elevation, azim=azimuth)
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_zlim(-1, 1)
    ax.set_xlabel("x")
    ax.set_ylabel("z")
    ax.set_zlabel("y (up)")
    ax.set_title(title, fontsize=8)
    return fig


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)
    _pyplot().close(fig)
    return path


def save_figure(fig, path: Path) -> None:
    """``fig`` as a PNG at ``path``, never written through a link planted there
    (:func:`sweeps.store.files.write_file`)."""
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=DPI, bbox_inches="tight")
    write_file(path, image.getvalue())
