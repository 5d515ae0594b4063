"""Metric names have one home (cdm/metric_names.py) and F1 is labelled at each run's own ``eval.f1_threshold``:
a sweep at τ = 0.02 says F1@0.02 in its table, plots and gallery, and F1@0.01 nowhere."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from cdm.config import load_config
from cdm.metric_names import TRAIN_METRICS, f1_at, f1_unit, label, metric_names
from sweeps.compare import plots
from sweeps.compare.gallery import grid_png
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.plots import PlotPoint, metric_vs_value, training_curves
from sweeps.compare.table import build_table

ROOT = Path(__file__).resolve().parents[1]


def _outcomes(threshold: float) -> list[TrialOutcome]:
    return [
        TrialOutcome(f"point_size={v} · seed 0", f"point_size={v}", "ok",
                     {"eval/f1": 0.3 + v, "eval/cd": 50 - v, "baseline/sphere/f1": 0.1, "baseline/sphere/cd": 70.0},
                     f1_threshold=threshold)
        for v in (0.02, 0.04)
    ]


def test_labels_name_the_threshold_they_are_given_in_world_units_and_each_of_several():
    assert f1_at(0.02) == "F1@0.02 sq. dist = 0.141421 world"
    assert label("eval/f1", 0.02) == "eval/f1 (F1@0.02 sq. dist = 0.141421 world)"
    assert label("eval/f1/chair", 0.04).endswith("(F1@0.04 sq. dist = 0.2 world)")
    assert label("eval/cd", 0.02) == "eval/cd (CD ×1000)" and label("train/lr", 0.02) == "train/lr"
    assert f1_unit([0.02, 0.02]).startswith("F1 is F1@0.02 on the squared distance: a point counts when it lies "
                                            "within 0.141421 in world units")
    assert f1_at([0.25, 0.01, 0.25]) == "F1@0.01 / 0.25 sq. dist (per cell)"
    assert "F1 is F1@0.01 / 0.25 on the squared distance" in f1_unit([0.01, 0.25])


def test_metric_names_are_written_once_and_the_plan_stage_lists_them_without_the_trainer():
    names = metric_names(["chair"])
    assert names[: len(TRAIN_METRICS)] == list(TRAIN_METRICS)
    assert {"eval/f1", "eval/cd/chair", "baseline/retrieval/f1/chair"} <= set(names) and len(names) == len(set(names))
    for path in ("sweeps/plan/trials.py", "cdm/train.py"):
        text = (ROOT / path).read_text()
        assert "def metric_names" not in text and '"train/loss"' not in text, path
    imported = {node.module for node in ast.walk(ast.parse((ROOT / "sweeps/plan/trials.py").read_text()))
                if isinstance(node, ast.ImportFrom)}
    assert "cdm.train" not in imported and "cdm.metric_names" in imported


def test_a_table_at_another_threshold_says_so_in_its_text_and_markdown():
    table = build_table(_outcomes(0.02), "eval/f1", "max", "t")
    assert table.f1_thresholds == (0.02,)
    for text in (table.text(), table.markdown()):
        flat = " ".join(text.split())
        assert "F1 is F1@0.02 on the squared distance" in flat and "within 0.141421 in world units" in flat
        assert "F1@0.01" not in flat and "within 0.1 in" not in flat
    default = build_table(_outcomes(load_config().eval.f1_threshold), "eval/f1", "max", "t")
    assert "F1 is F1@0.01 on the squared distance" in " ".join(default.text().split())


@pytest.fixture
def figure_texts(monkeypatch) -> list[str]:
    """Every text of every figure the plots save (titles, axis labels, legends), read from the figure objects."""
    texts: list[str] = []
    save = plots.save_figure

    def reading(fig, path):
        from matplotlib.text import Text

        texts.extend(t.get_text() for t in fig.findobj(Text))
        save(fig, path)

    monkeypatch.setattr(plots, "save_figure", reading)
    return texts


def test_plots_and_the_gallery_label_f1_at_the_runs_threshold(tmp_path, figure_texts):
    points = [PlotPoint(o.cell, {"priors.point_size": v}, o.metrics) for o, v in zip(_outcomes(0.02), (0.02, 0.04))]
    metric_vs_value(points, "eval/f1", "t", tmp_path / "a.png", f1_thresholds=0.02)
    history = {"train/loss": [(5, 3.0), (10, 2.0)], "train/loss_diffusion": [(5, 1.0), (10, 0.5)],
               "eval/f1": [(5, 0.3), (10, 0.4)]}
    training_curves({"a": history}, {"a": "a"}, "eval/f1", "t", tmp_path / "b.png", f1_thresholds=0.02)
    grid_png({"o1": {"a": np.zeros((8, 3))}}, ["a"], "t", tmp_path / "c.png", f1_thresholds=[0.02])
    with_f1 = [t for t in figure_texts if "F1@" in t]
    assert len(with_f1) == 3, figure_texts  # metric_vs_value's F1 axis, the curve's F1 axis, the gallery's title
    assert all("F1@0.02 sq. dist = 0.141421 world" in t for t in with_f1)
    assert not any("F1@0.01" in t for t in figure_texts)
