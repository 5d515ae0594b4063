"""Reconstructions of a sweep side by side: a PNG grid and a self-contained 3D viewer (HTML).

Rows are the same evaluated objects (one per category), columns the sweep's cells, then the ground
truth and the best baseline. Knows nothing of MLflow: :mod:`sweeps.results.publish` downloads the clouds and
hands them in as arrays. The viewer is one HTML file with its data and its JavaScript inline (no
network, no library), so MLflow's artifact view shows it as it is and it opens offline.
"""

from __future__ import annotations

import html
import json
import math
import re
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from cdm.io.files import read_text
from cdm.metric_names import f1_at
from sweeps.compare.plots import FONT, _pyplot, _save
from sweeps.store.files import write_file

__all__ = [
    "MIN_PANELS_ACROSS", "PANEL_IN", "Gallery", "Scores", "grid_figure", "grid_png", "panel_input", "viewer_html",
]

Gallery = Mapping[str, Mapping[str, np.ndarray]]
"""Object id → column label (a cell, ``ground truth``, ``baseline: …``) → its ``(N, 3)`` cloud."""

Scores = Mapping[str, Mapping[str, tuple[float, float]]]
"""Object id → column label → that object's ``(CD ×1000, F1)`` in that column (the ground truth has none)."""

ELEVATION, AZIMUTH = 20.0, 30.0
"""Degrees of the grid's fixed view (the panels' first view)."""


def _view(points: np.ndarray, elevation: float = ELEVATION, azimuth: float = AZIMUTH) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic screen ``(x, y)`` and depth of an ``(N, 3)`` cloud (world +Y up) seen from the
    given elevation/azimuth; larger depth is nearer the viewer."""
    a, e = math.radians(azimuth), math.radians(elevation)
    yaw = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    pitch = np.array([[1, 0, 0], [0, math.cos(e), -math.sin(e)], [0, math.sin(e), math.cos(e)]])
    p = points @ yaw.T @ pitch.T
    return p[:, :2], p[:, 2]


def panel_input(png: Path) -> np.ndarray | None:
    """The input image of an evaluation panel (``cdm.evaluate.save_panel``: its top-left square, framed by
    the axes' black border), as ``(H, W, 3)`` uint8; None when no such frame is found."""
    from cdm.io.images import read_rgb  # OpenCV, only when a panel is read

    rgb = read_rgb(png, "evaluation panel")
    if rgb is None:
        return None
    h, w = rgb.shape[:2]
    dark = rgb[: int(h * 0.6), : w // 4].mean(axis=2) < 80  # the input square: top row, first of four columns
    rows = np.flatnonzero(dark.mean(axis=1) > 0.5)
    if rows.size < 2:
        return None
    cols = np.flatnonzero(dark[rows[0]:rows[-1] + 1].mean(axis=0) > 0.9)
    if cols.size < 2 or rows[-1] - rows[0] < 10 or cols[-1] - cols[0] < 10:
        return None
    return rgb[rows[0] + 1:rows[-1], cols[0] + 1:cols[-1]]


PANEL_IN = 1.5
"""Side of one cloud's square in the grid, inches: the README shows the grid about 880 px wide, so a
grid of 8 columns (12 in at 150 dpi) is shown at ~0.5× and its 9-pt text ~9 px high."""

MIN_PANELS_ACROSS = 4
"""The grid is at least this many panels wide, so a grid of few columns still holds its heading's lines
(the metric names with their thresholds) unbroken."""


def _row_names(object_ids: Sequence[str]) -> tuple[list[str], str | None]:
    """Row labels: the object ids without the ``_``-separated words every id shares at its start and
    end (``procedural_airplane_val_00000`` → ``airplane``), and a note naming the full ids; the ids
    themselves when that would leave a row unnamed or two rows alike (one row, unrelated ids)."""
    words = [oid.split("_") for oid in object_ids]
    shortest = min((len(w) for w in words), default=0)
    head = next((i for i in range(shortest) if len({tuple(w[: i + 1]) for w in words}) > 1), shortest)
    tail = next((i for i in range(shortest - head) if len({tuple(w[len(w) - i - 1 :]) for w in words}) > 1),
                shortest - head)
    short = ["_".join(w[head : len(w) - tail]) for w in words]
    if len(words) < 2 or not (head or tail) or not all(short) or len(set(short)) < len(short):
        return list(object_ids), None
    pattern = "_".join([*words[0][:head], "<row>", *words[0][len(words[0]) - tail :]])
    return short, f"rows: objects {pattern}"


def _wrapped(label: str, font: float, panels: int = 1) -> str:
    """``label`` broken into lines that fit ``panels`` panels' width at ``font`` points (a character
    ~0.6 em wide, the widest of DejaVu Sans' lower case and digits)."""
    return textwrap.fill(label, width=max(8, int(panels * PANEL_IN * 72 / (0.6 * font))), break_on_hyphens=False)


def _draw_cell(ax, label: str, cloud: np.ndarray | None, image: np.ndarray | None) -> None:
    """One square of the grid: the input image, or a cloud (far points first), or nothing."""
    if image is not None:
        ax.imshow(image, extent=(-1, 1, -1, 1))
    elif cloud is not None:
        xy, depth = _view(cloud)
        order = np.argsort(depth)  # far points first, near ones drawn over them
        colour = "tab:green" if label == "ground truth" else "0.4" if label.startswith("baseline") else "tab:blue"
        ax.scatter(xy[order, 0], xy[order, 1], s=0.6, c=colour, alpha=0.85, linewidths=0)
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def grid_figure(gallery: Gallery, columns: Sequence[str], title: str, scores: Scores | None = None,
                inputs: Mapping[str, np.ndarray] | None = None, *, f1_thresholds: float | Sequence[float]):
    """The matplotlib figure of :func:`grid_png`, laid out (constrained layout: the title above the
    column titles, the row labels inside the figure; no two texts overlap)."""
    plt = _pyplot()
    rows = list(gallery)
    names, note = _row_names(rows)
    shown = (["input"] if inputs else []) + list(columns)
    across = max(len(shown), MIN_PANELS_ACROSS)
    size = (PANEL_IN * across + 0.4, (PANEL_IN + 0.35) * len(rows) + 0.9)  # inches: panels, their labels, heading
    fig, axes = plt.subplots(len(rows), len(shown), figsize=size, squeeze=False, layout="constrained")
    for r, oid in enumerate(rows):
        for c, label in enumerate(shown):
            ax = axes[r][c]
            image = inputs.get(oid) if inputs and label == "input" else None
            _draw_cell(ax, label, gallery[oid].get(label), image)
            score = (scores or {}).get(oid, {}).get(label)
            if score is not None:
                ax.set_xlabel(f"CD {score[0]:.1f} · F1 {score[1]:.3f}", fontsize=FONT)
            if r == 0:
                ax.set_title(_wrapped(label, FONT), fontsize=FONT)
            if c == 0:
                ax.set_ylabel(_wrapped(names[r], FONT), fontsize=FONT)
    heading = (title, f"CD ×1000 (lower is better) · {f1_at(f1_thresholds)} (higher is better)")
    fig.suptitle("\n".join(_wrapped(line, FONT + 1, across) for line in heading), fontsize=FONT + 1)
    if note:
        fig.supxlabel(note, fontsize=FONT)
    return fig


def grid_png(gallery: Gallery, columns: Sequence[str], title: str, path: Path, scores: Scores | None = None,
             inputs: Mapping[str, np.ndarray] | None = None, *, f1_thresholds: float | Sequence[float]) -> Path:
    """One row per object, one column per label in ``columns`` (missing clouds: an empty square), each
    cloud titled with its ``scores`` (CD ×1000, F1 at the trials' ``f1_thresholds``); with ``inputs``
    (object id → its input image), the image the model saw first. Rows are labelled by what tells their
    objects apart (:func:`_row_names`), the full ids under the grid."""
    return _save(grid_figure(gallery, columns, title, scores, inputs, f1_thresholds=f1_thresholds), path)


_PAGE = Path(__file__).with_name("viewer.html")
"""The viewer's page, its ``__TITLE__`` and ``__DATA__`` (the clouds, JSON) filled in by :func:`viewer_html`."""


def viewer_html(gallery: Gallery, columns: Sequence[str], title: str, path: Path, max_points: int = 2048,
                scores: Scores | None = None) -> Path:
    """A self-contained page that turns the clouds of each object, one canvas per column, in step.

    Each canvas is titled with its column and, from ``scores``, that object's CD (×1000) and F1 in
    it; canvases fill the window's width; nearer points are drawn larger and darker (a depth cue).
    Clouds are thinned to ``max_points`` (evenly, keeping their order) and rounded to 1/1000 of
    the unit cube, so a sweep of 8 objects × 7 columns stays a few MB at most.
    """
    objects = []
    for oid, clouds in gallery.items():
        shown = {}
        for label in columns:
            if label in clouds:
                cloud = clouds[label][:: max(1, math.ceil(len(clouds[label]) / max_points))]
                shown[label] = np.round(cloud.astype(float), 3).tolist()
        found = (scores or {}).get(oid, {})
        objects.append({"id": oid, "clouds": shown, "scores": {k: list(v) for k, v in found.items() if k in shown}})
    # "</" cannot end the inline script early: JSON allows the escaped form.
    data = json.dumps({"columns": list(columns), "objects": objects}, separators=(",", ":")).replace("</", "<\\/")
    fill = {"__TITLE__": html.escape(title), "__DATA__": data}
    path.parent.mkdir(parents=True, exist_ok=True)
    # One pass: an object id or title spelling a marker is not filled in again.
    write_file(path, re.sub("__TITLE__|__DATA__", lambda m: fill[m[0]], read_text(_PAGE, "the viewer's page")))
    return path
