"""The reconstructions grid (sweeps/compare/gallery.py): row names, and a layout whose texts neither
overlap nor leave the figure, measured on the drawn figure's text extents."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from sweeps.compare.gallery import PANEL_IN, _row_names, grid_figure, grid_png
from sweeps.compare.plots import DPI

CATEGORIES = ("airplane", "bottle", "chair", "lamp", "mug", "ring", "sofa", "table")
MAIN_JOB_COLUMNS = [f"point_size={v}" for v in (0.0075, 0.01, 0.02, 0.04, 0.08)] + [
    "ground truth", "baseline: category_mean"]


def _gallery(object_ids, columns, seed=0):
    rng = np.random.default_rng(seed)
    clouds = {oid: {label: rng.normal(0.0, 0.3, (64, 3)) for label in columns} for oid in object_ids}
    # CD ×1000 of a bad cell reaches the hundreds (the ring's 234.4 in the README's grid): the widest label
    scores = {oid: {label: (234.4, 0.012) for label in columns if label != "ground truth"} for oid in object_ids}
    inputs = {oid: rng.integers(0, 256, (32, 32, 3), dtype=np.uint8) for oid in object_ids}
    return clouds, scores, inputs


def test_row_names_drop_the_words_all_ids_share_and_name_the_full_ids_once():
    ids = [f"procedural_{c}_val_00000" for c in CATEGORIES]
    assert _row_names(ids) == (list(CATEGORIES), "rows: objects procedural_<row>_val_00000")
    assert _row_names(["shapenet_chair_1a2b", "shapenet_chair_3c4d"]) == (
        ["1a2b", "3c4d"], "rows: objects shapenet_chair_<row>")
    # one row, ids with nothing in common, or ids that only differ in a shared word: the ids as they are
    for ids in (["procedural_chair_val_00000"], ["a_b", "c_d"], ["x_a_y", "x_a_b_y", "x_y"]):
        assert _row_names(ids) == (ids, None)


def _texts(fig):
    from matplotlib.text import Text

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    return [(t.get_text(), t.get_window_extent(renderer)) for t in fig.findobj(Text)
            if t.get_visible() and t.get_text().strip()]


@pytest.mark.parametrize("case", ["main job", "long names"])
def test_grid_texts_neither_overlap_nor_leave_the_figure(case):
    """The README's grid (8 objects × input, 5 cells, ground truth, baseline) and one with long cell labels
    and row ids that share nothing: every title, column title, row label and score lies inside the
    figure, and no two of them share a pixel (the title once ran into the column titles)."""
    if case == "main job":
        ids, columns = [f"procedural_{c}_val_00000" for c in CATEGORIES], MAIN_JOB_COLUMNS
    else:
        ids = ["02691156_1a04e3eab45ca15dd86060f189eb133a", "chair_17_scene_0003_frame_000112", "lamp"]
        columns = ["priors.point_size=0.02, priors.lambda_3d=0.1, train.lr=3e-4", "priors.point_size=0.04",
                   "ground truth", "baseline: category_mean"]
    clouds, scores, inputs = _gallery(ids, columns)
    title = "point_size — profile local: reconstructions at the last evaluation of every cell of the sweep"
    fig = grid_figure(clouds, columns, title, scores, inputs, f1_thresholds=0.01)
    texts = _texts(fig)
    try:
        shown = [t for t, _ in texts]
        assert sum("CD 234.4 · F1 0.012" == t for t in shown) == len(ids) * (len(columns) - 1)
        assert shown.count(fig.get_suptitle()) == 1 and fig.get_suptitle().startswith("point_size — profile local")
        figure = fig.bbox
        for text, box in texts:
            assert (box.x0 >= figure.x0 and box.y0 >= figure.y0 and box.x1 <= figure.x1
                    and box.y1 <= figure.y1), (text, box.bounds, figure.bounds)
        for (a, box_a), (b, box_b) in itertools.combinations(texts, 2):
            width = min(box_a.x1, box_b.x1) - max(box_a.x0, box_b.x0)
            height = min(box_a.y1, box_b.y1) - max(box_a.y0, box_b.y0)
            assert width <= 0 or height <= 0, (a, b, box_a.bounds, box_b.bounds)
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)


def test_grid_png_writes_the_laid_out_figure(tmp_path):
    from cdm.io.images import read_rgb

    ids = [f"procedural_{c}_val_00000" for c in CATEGORIES[:2]]
    clouds, scores, inputs = _gallery(ids, MAIN_JOB_COLUMNS)
    path = grid_png(clouds, MAIN_JOB_COLUMNS, "t", tmp_path / "grid.png", scores, inputs, f1_thresholds=0.01)
    rgb = read_rgb(path, "grid")
    height, width = rgb.shape[:2]
    assert width == pytest.approx((1 + len(MAIN_JOB_COLUMNS)) * PANEL_IN * DPI, rel=0.1)  # input + 7 panels
    assert 2.0 < width / height < 3.5  # 8 columns, 2 rows and the heading
    assert (rgb < 128).any() and (rgb > 250).any()
