"""Reports rebuilt from a real MLflow SQLite store, written by the tracking classes the runner uses.

No Ray here: each sweep's runs are written with :class:`SweepRun`/:class:`TrialRun` exactly as the
driver and the trials write them, with chosen numbers, so the report's every figure can be checked.
The end-to-end version (a real smoke sweep, the notebook, the MLflow UI) is
``tests/integration/test_compare.py``.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import torch
from mlflow import MlflowClient
from scipy.ndimage import binary_dilation

from cdm.data import build_dataset
from cdm.data.sample import collate
from cdm.evaluate import save_panel
from cdm.metric_names import COMPUTE_METRIC, rounded
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.table import build_table
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from sweeps.results import publish
from sweeps.results.sweep import open_sweep, paper_layout, protocol_card_lines, results_table, trial_records
from sweeps.store.sweep_run import SweepRun, baselines_by_eval_set, with_logged_baselines
from sweeps.store.trial_run import TrialRun
from tests.conftest import tiny_config

GRID = """name: synth
paper:
  table: Table 5
  note: Co3D teddybear
  rows:
    - {label: "size 0.02", when: {priors.point_size: 0.02}, values: {eval/f1: 0.45, eval/cd: 110.0}}
    - {label: "size 0.04", when: {priors.point_size: 0.04}, values: {eval/f1: 0.46, eval/cd: 105.0}}
grid: {priors.point_size: [0.02, 0.04, 0.08]}
"""

OPTUNA = """name: synth_opt
search:
  kind: optuna
  num_samples: 4
  space: {priors.lambda_3d: {type: log_float, low: 1.0e-3, high: 10.0}}
metric: {name: eval/cd, mode: min}
"""


def _start(tmp_path: Path, uri: str, text: str) -> tuple[SweepRun, object]:
    """The parent run as ``sweeps/run.py`` opens it: spec file and plan.json as artifacts."""
    spec_file = tmp_path / f"{text.split()[1]}.yaml"
    spec_file.write_text(text)
    plan = expand(load_spec(spec_file), "smoke")
    sweep = SweepRun.start(
        uri,
        plan.spec.name,
        f"{plan.spec.name} · smoke",
        tags={"spec": plan.spec.name, "profile": "smoke"},
        params={"trials": plan.num_trials},
    )
    plan_file = tmp_path / "plan.json"
    plan_file.write_text(json.dumps({"fixed": plan.fixed, "sets": {}, "cells": [
        {"label": c.label, "values": c.values, "seed": c.seed, "paper": c.paper} for c in plan.cells]}, default=str))
    sweep.log_artifacts([spec_file, plan_file])
    return sweep, plan


def _trial(
    tmp_path: Path,
    sweep: SweepRun,
    trial_id: str,
    label: str,
    overrides: dict,
    evals: dict[int, dict[str, float]],
    objects: list[dict[str, object]] | None = None,
) -> TrialRun:
    """A trial's child run fed as ``cdm.train.fit`` feeds it: losses, then evaluations (the last with objects.csv)."""
    cell = label.rsplit(" · seed ", 1)[0]
    run = TrialRun(sweep.uri, sweep.experiment_id, sweep.run_id, trial_id, label,
                   {"cell": cell, "group": cell.split("=")[-1], "seed": "0"}, tiny_config(tmp_path, **overrides))
    for step in (5, 10, 15, 20):
        run.on_step(step, {"train/loss": 10.0 / step})
    for step, metrics in evals.items():
        files = []
        if objects is not None and step == max(evals):
            table = tmp_path / trial_id / "objects.csv"
            table.parent.mkdir(parents=True, exist_ok=True)
            with table.open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=list(objects[0]))
                writer.writeheader()
                writer.writerows(objects)
            files.append(table)
        run.on_eval(step, metrics, files)
    return run


def _objects(cd: list[float]) -> list[dict[str, object]]:
    return [{"object_id": f"o{i}", "category": "chair", "eval_set": "e1", "cd": v, "f1": 0.5 - v / 1000,
             "baseline/sphere/cd": 150.0, "baseline/sphere/f1": 0.2} for i, v in enumerate(cd)]


@pytest.fixture(scope="module")
def grid_store(tmp_path_factory):
    """Three cells: two finished (point sizes 0.02 and 0.04), one failed before its first evaluation."""
    tmp_path = tmp_path_factory.mktemp("grid")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep, plan = _start(tmp_path, uri, GRID)
    labels = [c.label for c in plan.cells]
    base = {"baseline/sphere/cd": 150.0, "baseline/sphere/f1": 0.2, "baseline/sphere/f1/chair": 0.21}
    _trial(tmp_path, sweep, "t0", labels[0], {"priors.point_size": 0.02},
           {10: {"eval/cd": 90.0, "eval/f1": 0.40, **base, "eval/cd/chair": 91.0, "eval/f1/chair": 0.41},
            20: {"eval/cd": 80.0, "eval/f1": 0.42, **base, "eval/cd/chair": 81.0, "eval/f1/chair": 0.43}},
           _objects([70.0, 80.0, 90.0]))
    _trial(tmp_path, sweep, "t1", labels[1], {"priors.point_size": 0.04},
           {20: {"eval/cd": 60.0, "eval/f1": 0.48, **base, "eval/cd/chair": 61.0, "eval/f1/chair": 0.49}},
           _objects([50.0, 60.0, 70.0]))
    # The driver closes each with Tune's last result, the source of the per-category finals.
    sweep.close_trial(
        "t0",
        labels[0],
        "FINISHED",
        last={"eval/cd": 80.0, "eval/f1": 0.42, "eval/cd/chair": 81.0, "eval/f1/chair": 0.43},
    )
    sweep.close_trial(
        "t1",
        labels[1],
        "FINISHED",
        last={"eval/cd": 60.0, "eval/f1": 0.48, "eval/cd/chair": 61.0, "eval/f1/chair": 0.49},
    )
    # The driver's verdict for a trial that raised before it opened its run (_TrialCloser.on_trial_error).
    sweep.close_trial("t2", labels[2], "FAILED", error="cdm.train.TrainingDiverged: loss became NaN at step 3")
    # The driver's end of the sweep: the baselines once for the evaluation set, on the parent.
    sweep.log_results({"e1": base}, "synth: a grid")
    sweep.end()
    return uri, sweep


def test_final_metrics_are_the_last_evaluation_under_stable_names(grid_store):
    uri, sweep = grid_store
    client = MlflowClient(uri)
    runs = {
        r.info.run_name: r
        for r in client.search_runs([sweep.experiment_id], f"tags.mlflow.parentRunId = '{sweep.run_id}'")
    }
    first = runs["point_size=0.02 · seed 0"]
    assert first.data.metrics["final/cd"] == 80.0 and first.data.metrics["final/f1"] == 0.42
    assert first.data.metrics["final/cd/chair"] == 81.0 and first.data.metrics["final/f1/chair"] == 0.43
    assert [m.step for m in client.get_metric_history(first.info.run_id, "final/cd")] == [20]
    # Per category one value each, a final/… metric MLflow filters on; no eval/<metric>/<category> series.
    assert not [k for k in first.data.metrics if k.count("/") >= 2 and not k.startswith("final/")]
    assert not [k for k in first.data.params if k.startswith("final/")]
    assert not any(k.startswith("final/") for k in runs["point_size=0.08 · seed 0"].data.metrics)  # failed: no final
    # The parent: the baselines' scores, overall and per category, as metrics; no metric per cell.
    parent = client.get_run(sweep.run_id).data
    assert {k: v for k, v in parent.metrics.items() if k.count("/") == 2} == {"baseline/sphere/cd": 150.0,
                                                                             "baseline/sphere/f1": 0.2}
    assert parent.metrics["baseline/sphere/f1/chair"] == 0.21 and not [k for k in parent.params if "baseline/" in k]


def test_report_rebuilds_the_table_with_the_failed_trial_as_failed(grid_store, tmp_path, capsys):
    uri, _ = grid_store
    out = tmp_path / "report"
    assert publish.main(["synth", "--tracking-uri", uri, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows = {line.split("  ")[0].rstrip(" ★"): line for line in text.splitlines() if line.startswith("point_size=")}
    assert set(rows) == {"point_size=0.02", "point_size=0.04", "point_size=0.08"}
    assert (
        "0/1 (1 failed)" in rows["point_size=0.08"] and "failed" in rows["point_size=0.08"].split("0/1 (1 failed)")[1]
    )
    assert "0.420" in rows["point_size=0.02"] and "0.450" in rows["point_size=0.02"]  # ours beside the paper's
    assert rows["point_size=0.04"].startswith("point_size=0.04 ★")  # best F1
    # Paired with the first cell on the same 3 objects: every object 20 lower, so Δcd is exactly -20
    # (in results.md: the terminal shows the Δ of the sweep's metric, F1, within 120 columns).
    assert "+0.020 [+0.020, +0.020]" in rows["point_size=0.04"] and "better" in rows["point_size=0.04"]
    assert (
        max(len(line) for line in text.split("\nresults: ")[0].splitlines()) <= 120
    )  # the table, not the paths after it
    md_row = next(
        line for line in (out / "results.md").read_text().splitlines() if line.startswith("| point_size=0.04")
    )
    assert "-20.00 [-20.00, -20.00]" in md_row
    # The baseline comes from the parent run (logged once there, not on the children).
    assert "baseline: sphere" in text
    assert "best cell point_size=0.04 (Δf1 +0.020 [+0.020, +0.020] against the next cell): beats sphere" in " ".join(
        text.split()
    )
    assert "failed: point_size=0.08 · seed 0 — cdm.train.TrainingDiverged: loss became NaN at step 3" in text
    records = list(csv.DictReader((out / "results.csv").open()))
    assert [r["cell"] for r in records[:3]] == ["point_size=0.02", "point_size=0.04", "point_size=0.08"]
    assert float(records[1]["eval/f1 mean"]) == 0.48 and float(records[1]["eval/f1 paper"]) == 0.46
    assert records[2]["failed"] == "1" and records[2]["eval/f1 mean"] == ""
    for name in ("metric_vs_value.png", "training_curves.png"):
        assert mpimg.imread(out / name).std() > 0.01  # a drawn figure, not a blank one


def test_report_writes_the_runners_results_csv_byte_for_byte(tmp_path):
    """Numbers no table prints whole (0.4213456789…): MLflow keeps every digit, so the report's results.csv
    equals the runner's, made as ``sweeps/execute/driver.py`` makes it from Tune's results."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep, plan = _start(tmp_path, uri, GRID.replace("name: synth", "name: digits"))
    base = {"baseline/sphere/cd": 150.01234567891, "baseline/sphere/f1": 0.2012345678901,
            "baseline/sphere/f1/chair": 0.2112345678901, "baseline/sphere/cd/chair": 151.0987654321}
    outcomes = []
    for i, cell in enumerate(plan.cells[:2]):
        last = {"eval/cd": 80.123456789 - 20 * i, "eval/f1": 0.4213456789012 + 0.06 * i, **base,
                "train/compute_s": 3.0123456789012 + i,
                "eval/cd/chair": 81.98765432 - 20 * i, "eval/f1/chair": 2 / 3 + 0.01 * i}
        objects = [{"object_id": f"o{k}", "category": "chair", "eval_set": "e1", "cd": 70.1234567 + 10 * k - 20 * i,
                    "f1": 0.5 - k / 700 + i / 30, "baseline/sphere/cd": 150 + k / 3, "baseline/sphere/f1": 0.2 + k / 7}
                   for k in range(3)]
        _trial(tmp_path, sweep, f"t{i}", cell.label, cell.values, {20: last}, objects)
        sweep.close_trial(f"t{i}", cell.label, "FINISHED", last=last)
        outcomes.append(TrialOutcome(cell.label, cell.name, "ok", {**last, "step": 20.0}, cell.paper_label,
                                     cell.paper, None, tuple(objects), cell.config.eval.f1_threshold))
    sweep.close_trial("t2", plan.cells[2].label, "FAILED", error="died")
    outcomes.append(TrialOutcome(plan.cells[2].label, plan.cells[2].name, "failed", {}, plan.cells[2].paper_label,
                                 plan.cells[2].paper, "died", (), plan.cells[2].config.eval.f1_threshold))
    baselines = baselines_by_eval_set(outcomes)
    runner = build_table(with_logged_baselines(outcomes, baselines), "eval/f1", "max", "digits — profile smoke",
                         settings=["s"])
    _, ours = runner.write(tmp_path / "runner")
    sweep.log_results(baselines, "digits")
    sweep.end()
    assert publish.main(["digits", "--tracking-uri", uri, "--out", str(tmp_path / "report")]) == 0
    theirs = (tmp_path / "report" / "results.csv").read_bytes()
    assert theirs == ours.read_bytes() and b"0.4213456789012," in theirs and b"0.6666666666666666," in theirs
    assert b",train/compute_s mean," in theirs and b",3.0123456789012," in theirs  # the cost column


def test_paper_layout_puts_ours_beside_the_paper_per_cell(grid_store):
    uri, _ = grid_store
    record = open_sweep(uri, "synth")
    table = paper_layout(trial_records(record, objects=False))
    assert list(table.index) == ["point_size=0.02", "point_size=0.04", "point_size=0.08"]
    assert (
        table.loc["point_size=0.02", ("all", "F1 ours")] == 0.42
        and table.loc["point_size=0.02", ("all", "F1 paper")] == 0.45
    )
    assert (
        table.loc["point_size=0.04", ("all", "CD ours")] == 60.0
        and table.loc["point_size=0.04", ("all", "CD paper")] == 105.0
    )
    assert table.loc["point_size=0.04", ("chair", "F1 ours")] == 0.49
    assert table.loc["point_size=0.08", ("", "trials")] == "0/1 (1 failed)" and np.isnan(
        table.loc["point_size=0.08", ("all", "CD ours")]
    )


def test_unknown_experiment_exits_2_listing_the_known_ones(grid_store, capsys):
    uri, _ = grid_store
    assert publish.main(["point_sise", "--tracking-uri", uri]) == 2
    assert capsys.readouterr().err.strip() == "error: no MLflow experiment named 'point_sise'; known: Default, synth"


def test_child_description_says_cell_result_verdict_and_links_the_parent(grid_store):
    uri, sweep = grid_store
    record = open_sweep(uri, "synth")
    trials = trial_records(record)
    table = results_table(record, trials)
    raw = {t.outcome.cell: publish.describe_trial(record, t, table) for t in trials}
    assert max(len(line) for d in raw.values() for line in d.splitlines()) <= publish.DESCRIPTION_WIDTH
    text = {cell: " ".join(d.split()) for cell, d in raw.items()}  # Markdown joins the wrapped lines
    # workflowType: MLflow's model training view
    link = f"(#/experiments/{sweep.experiment_id}/runs/{sweep.run_id}?workflowType=machine_learning)"
    assert text["point_size=0.04"] == (
        f"**point_size=0.04**, seed 0, a trial of the sweep [synth — profile smoke]{link}. At its last "
        "evaluation eval/f1 (F1@0.01 sq. dist = 0.1 world) 0.48, eval/cd (CD ×1000) 60.0. "
        "Its cell against the reference "
        "cell: Δf1 +0.020 [+0.020, +0.020] "
        "(95% paired interval), better. Baselines it beats on eval/f1: sphere."
    )
    assert "It failed: cdm.train.TrainingDiverged: loss became NaN at step 3." in text["point_size=0.08"]
    assert "Its cell is the reference cell the others are paired with." in text["point_size=0.02"]


def test_training_curves_split_the_loss_and_draw_the_evaluations(tmp_path):
    from PIL import Image

    from sweeps.compare.plots import training_curves

    loss = {"train/loss": [(5, 3.0), (10, 2.0)], "train/loss_diffusion": [(5, 1.0), (10, 0.5)]}
    none = training_curves({"a": loss}, {"a": "a"}, "eval/f1", "t", tmp_path / "none.png", f1_thresholds=0.01)
    once = training_curves({"a": loss | {"eval/f1": [(10, 0.4)]}}, {"a": "a"}, "eval/f1", "t", tmp_path / "once.png",
                           f1_thresholds=0.01)
    # Diffusion, λ × prior and total side by side; the evaluations in a fourth panel, even a single one.
    (w0, h0), (w1, h1) = Image.open(none).size, Image.open(once).size
    assert 2.5 < w0 / h0 < 3.5 and 3.4 < w1 / h1 < 4.8


def test_baselines_once_on_the_parent_and_no_per_trial_paths_in_params(grid_store):
    uri, sweep = grid_store
    client = MlflowClient(uri)
    parent = client.get_run(sweep.run_id)
    assert parent.data.metrics["baseline/sphere/f1"] == 0.2 and not [
        k for k in parent.data.metrics if "point_size" in k
    ]
    assert parent.data.tags["mlflow.note.content"] == "synth: a grid"
    for child in client.search_runs([sweep.experiment_id], f"tags.mlflow.parentRunId = '{sweep.run_id}'"):
        assert not [k for k in child.data.metrics if k.startswith("baseline/")]
        assert "train.out_dir" not in child.data.params
        assert child.data.params or child.data.tags.get("error")  # the failed one never logged its config


def test_parent_description_puts_the_verdicts_and_a_narrow_table_first(grid_store):
    uri, _ = grid_store
    record = open_sweep(uri, "synth")
    table = results_table(record, trial_records(record))
    card = protocol_card_lines(record)
    text = publish.describe_sweep(record.spec, "smoke", "tiny", table, card)
    blocks = text.split("\n\n")
    assert blocks[0] == ("**synth**, profile **smoke**, by eval/f1 (higher is better): best cell point_size=0.04 "
                         "(Δf1 +0.020 [+0.020, +0.020] against the next cell): beats sphere.")
    # The narrow table: cell, metric, partner, Δ with its interval, verdict; no paper or per-category column.
    assert blocks[1].splitlines()[0] == "| cell | eval/f1 | eval/cd | Δf1 vs point_size=0.02 [95% CI] | verdict |"
    assert "| point_size=0.04 ★ | 0.480 | 60.00 | +0.020 [+0.020, +0.020] | better |" in blocks[1]
    assert "`results.md`" in text.split("| verdict |")[1].split("\n\n")[2]
    assert text.index("**Protocol card**") > text.index("| verdict |") and text.count(card[0].split(" (")[0]) == 1
    assert blocks[-1] == "Profile **smoke**: tiny"


def test_description_lines_are_short_and_every_number_rounded(grid_store):
    uri, _ = grid_store
    record = open_sweep(uri, "synth")
    table = results_table(record, trial_records(record))
    long_card = ["deviation: train.steps: 20, not 100000 (" + "a source " * 40 + ")"]
    text = publish.describe_sweep(record.spec, "smoke", "a profile " * 40, table, long_card)
    assert max(len(line) for line in text.splitlines()) <= 200
    # The tables' precision: 3 decimals below 10, 2 above; no 16-digit float (0.42000000000000004).
    assert not re.findall(r"\d\.\d{4,}", text)
    assert rounded(0.42000000000000004) == 0.42 and rounded(60.942297) == 60.94
    assert rounded(1.23456) == 1.235 and math.isnan(rounded(math.nan))


def test_optuna_sweep_gets_history_and_importance_plots(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep, _ = _start(tmp_path, uri, OPTUNA)
    for i, (lam, cd) in enumerate([(0.01, 70.0), (0.1, 60.0), (1.0, 90.0)]):
        label = f"λ={lam:g} · seed 0"
        scores = {"eval/cd": cd, "eval/f1": 0.4 + i / 10, COMPUTE_METRIC: 10.0 * (3 - i)}
        _trial(tmp_path, sweep, f"t{i}", label, {"priors.lambda_3d": lam}, {20: scores})
        sweep.close_trial(f"t{i}", label, "FINISHED")
    _trial(tmp_path, sweep, "t3", "λ=5 · seed 0", {"priors.lambda_3d": 5.0}, {})
    sweep.close_trial("t3", "λ=5 · seed 0", "FAILED", error="boom")
    record = open_sweep(uri, "synth_opt")
    trials = trial_records(record, objects=False)
    assert [t.outcome.label for t in trials] == ["λ=0.1 · seed 0", "λ=0.01 · seed 0", "λ=1 · seed 0", "λ=5 · seed 0"]
    assert [t.values["priors.lambda_3d"] for t in trials] == [0.1, 0.01, 1.0, 5.0]
    paths = publish.write_plots(record, trials, tmp_path / "plots")
    assert [p.name for p in paths] == [
        "metric_vs_value.png",
        "training_curves.png",
        "optuna_history.png",
        "optuna_importance.png",
        "optuna_pareto.png",
    ]
    for p in paths:
        assert mpimg.imread(p).std() > 0.01


def panel_views(png: Path) -> list[np.ndarray]:
    """The 6 cloud views of a panel (prediction 0–2 from the top row, then ground truth 0–2 from the
    bottom row) as boolean "ink" masks of equal shape.

    Each row is read on its own: columns dark over most of the row's height are the axes' frame lines,
    and the 6 rightmost of a row come in pairs (the last 3 axes of the row).
    """
    img = mpimg.imread(png)[..., :3]
    dark_all = (img < 0.25).all(-1)
    frame_rows = np.flatnonzero(dark_all.mean(1) > 0.5)  # the top and bottom lines of both rows of axes
    bands = [(r[0], r[-1]) for r in np.split(frame_rows, np.flatnonzero(np.diff(frame_rows) > 1) + 1)]
    assert len(bands) == 4, f"expected 2 rows of axes, found frame lines at {bands}"
    views = []
    for (top, _), (_, bottom) in zip(bands[0::2], bands[1::2]):
        band = img[top:bottom + 1]
        dark = dark_all[top:bottom + 1]
        cols = np.flatnonzero(dark.mean(0) > 0.5)
        lines = [(c[0], c[-1]) for c in np.split(cols, np.flatnonzero(np.diff(cols) > 1) + 1)][-6:]
        for (_, left), (right, _) in zip(lines[0::2], lines[1::2]):
            inner = band[3:-3, left + 2:right - 1]
            views.append((inner < 0.9).any(-1))
    h = min(v.shape[0] for v in views)
    w = min(v.shape[1] for v in views)
    return [v[:h, :w] for v in views]


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Share of ink of each mask within 2 px of the other's ink, the smaller of the two (1: same drawing).

    2 px of tolerance: two axes of one figure land on the pixel grid with different sub-pixel offsets.
    """
    near_a, near_b = binary_dilation(a, iterations=2), binary_dilation(b, iterations=2)
    return float(min((a & near_b).sum() / a.sum(), (b & near_a).sum() / b.sum()))


def test_panel_views_match_where_the_clouds_match_and_differ_where_they_differ(tmp_path):
    cfg = tiny_config(tmp_path)
    batch = collate([build_dataset(cfg, "val")[0]])
    gt = batch.points[0]
    same = panel_views(save_panel(tmp_path / "same.png", batch, 0, gt.clone(), 0.0, 1.0))
    assert len(same) == 6 and all(v.sum() > 30 for v in same)
    for k in range(3):  # prediction = ground truth: each pred view draws what the GT view draws
        assert _overlap(same[k], same[3 + k]) > 0.95
    assert _overlap(same[3], same[4]) < 0.8  # and the 3 views are different views
    moved = panel_views(
        save_panel(tmp_path / "moved.png", batch, 0, gt * 0.3 + torch.tensor([0.4, 0.0, 0.0]), 50.0, 0.1)
    )
    for k in range(3):
        assert _overlap(moved[k], moved[3 + k]) < 0.4
        assert _overlap(moved[3 + k], same[3 + k]) > 0.95  # the GT half does not depend on the prediction
    # The reconstructions grid takes the input image back from the panel: the object's own pixels, resized.
    from PIL import Image

    from sweeps.compare.gallery import panel_input

    shown = panel_input(tmp_path / "same.png")
    image = (batch.image[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    assert shown is not None and shown.shape[0] > 4 * image.shape[0]
    back = np.asarray(Image.fromarray(shown).resize(image.shape[1::-1], Image.NEAREST)).astype(int)
    assert np.abs(back - image).mean() < 20


def test_metric_vs_value_log_axis_baseline_lines_and_resolution(tmp_path):
    from PIL import Image

    from sweeps.compare.plots import PlotPoint, log_spaced, metric_vs_value

    assert log_spaced([0.0075, 0.01, 0.02, 0.04, 0.08]) and log_spaced([1e-3, 1e-2, 1e-1, 1.0])
    assert not log_spaced([1, 2, 3, 4]) and not log_spaced([0.02, 0.04]) and not log_spaced([0.0, 0.1, 1.0])
    points = [
        PlotPoint(
            f"point_size={v}",
            {"priors.point_size": v},
            {"eval/f1": 0.3 + v, "eval/cd": 50 - v, "baseline/sphere/f1": 0.1, "baseline/sphere/cd": 20.0},
        )
        for v in (0.0075, 0.01, 0.02, 0.04, 0.08)
    ]
    with_baseline = metric_vs_value(points, "eval/f1", "t", tmp_path / "a.png", "Table 5", f1_thresholds=0.01)
    without = metric_vs_value(
        [PlotPoint(p.cell, p.values, {k: v for k, v in p.metrics.items() if k.startswith("eval/")}) for p in points],
        "eval/f1",
        "t",
        tmp_path / "b.png",
        f1_thresholds=0.01,
    )
    image = Image.open(with_baseline)
    assert image.info["dpi"][0] == pytest.approx(150, abs=1)
    pixels = np.asarray(image.convert("RGB")).astype(int)

    def grey(px):  # pixels of the 0.45-grey dashed reference lines (antialiased: roughly that grey)
        return int(((np.abs(px - 115).max(axis=2) < 40) & (np.ptp(px, axis=2) < 6)).sum())

    # Two panels × one baseline line across each (~600 px wide, ~2 px thick, dashed).
    assert grey(pixels) - grey(np.asarray(Image.open(without).convert("RGB")).astype(int)) > 1000


def test_reconstructions_grid_and_viewer_compare_cells_on_the_same_objects(tmp_path):
    from PIL import Image

    from cdm.evaluate import write_ply

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep, plan = _start(tmp_path, uri, GRID)
    labels = [c.label for c in plan.cells]
    rng = np.random.default_rng(0)
    clouds = {}
    base = {
        "baseline/sphere/f1": 0.2,
        "baseline/retrieval/f1": 0.6,
        "baseline/sphere/cd": 90.0,
        "baseline/retrieval/cd": 30.0,
    }
    for i, label in enumerate(labels[:2]):
        folder = tmp_path / f"eval{i}"
        files = []
        for oid in ("chair_0001", "mug_0002"):
            for suffix in ("", ".gt", ".sphere", ".retrieval", ".gaussian", ".category_mean"):
                cloud = clouds.setdefault(
                    (oid, suffix if suffix else label), torch.from_numpy(rng.uniform(-0.5, 0.5, (300, 3))).float()
                )
                files.append(write_ply(folder / f"{oid}{suffix}.ply", cloud))
        table = folder / "objects.csv"
        table.write_text("object_id,category,eval_set,cd,f1,baseline/retrieval/cd,baseline/retrieval/f1\n"
                         + "".join(f"{oid},c,e1,{40 + 10 * i + j},{0.5 - 0.1 * i},30.0,0.6\n"
                                   for j, oid in enumerate(("chair_0001", "mug_0002"))))
        files.append(table)
        run = TrialRun(
            uri,
            sweep.experiment_id,
            sweep.run_id,
            f"t{i}",
            label,
            {"cell": label.split(" · ")[0], "seed": "0"},
            tiny_config(tmp_path),
        )
        run.on_eval(20, {"eval/f1": 0.4, "eval/cd": 50.0}, files)
        sweep.close_trial(f"t{i}", label, "FINISHED")
    sweep.log_results({"e1": base}, "grid")
    sweep.end()
    record = open_sweep(uri, "synth")
    png, page = publish.reconstructions(record, trial_records(record, objects=False), tmp_path / "out")
    width, height = Image.open(png).size
    assert width > 1.3 * height  # 4 columns (2 cells, GT, best baseline) × 2 rows, under a two-line heading
    text = page.read_text()
    assert "<canvas" not in text and 'createElement("canvas")' in text  # drawn by the inline script
    assert "src=" not in text and "http" not in text  # self-contained: nothing fetched
    data = json.loads(text.split('type="application/json">', 1)[1].split("</script>", 1)[0])
    cells = [label.split(" · ")[0] for label in labels[:2]]
    assert data["columns"] == [*cells, "ground truth", "baseline: retrieval"]  # retrieval: the best F1
    first = data["objects"][0]
    assert [o["id"] for o in data["objects"]] == ["chair_0001", "mug_0002"] and set(first["clouds"]) == set(
        data["columns"]
    )
    assert np.allclose(first["clouds"][cells[1]], clouds[("chair_0001", labels[1])].numpy(), atol=5e-4)
    assert np.allclose(first["clouds"]["ground truth"], clouds[("chair_0001", ".gt")].numpy(), atol=5e-4)
    # Each canvas's title: that object's CD and F1 in that column (objects.csv); none for the ground truth.
    assert first["scores"] == {cells[0]: [40.0, 0.5], cells[1]: [50.0, 0.4], "baseline: retrieval": [30.0, 0.6]}
    assert data["objects"][1]["scores"][cells[1]] == [51.0, 0.4]
