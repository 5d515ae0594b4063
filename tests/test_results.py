"""Results table: mean ± std over seeds, the paper's number beside it, best cell, baselines, failures."""

from __future__ import annotations

import csv
import statistics

import pytest
import torch

from sweeps.results import TrialOutcome, build_table, settings_note


def _trial(cell, seed, status="ok", **metrics):
    return TrialOutcome(f"{cell} · seed {seed}", cell, status, {k.replace("__", "/"): v for k, v in metrics.items()},
                        paper_label="p" if cell == "a" else None, paper={"eval/f1": 0.461, "eval/f1/chair": 0.476} if cell == "a" else {})


OUTCOMES = [
    _trial("a", 0, eval__f1=0.40, eval__cd=80.0, eval__f1__chair=0.30, baseline__sphere__f1=0.10, baseline__sphere__cd=90.0),
    _trial("a", 1, eval__f1=0.50, eval__cd=70.0, eval__f1__chair=0.40, baseline__sphere__f1=0.12, baseline__sphere__cd=92.0),
    _trial("b", 0, eval__f1=0.42, eval__cd=60.0, eval__f1__chair=0.20, baseline__sphere__f1=0.10, baseline__sphere__cd=90.0),
    TrialOutcome("b · seed 1", "b", "failed", error="TrainingDiverged: loss became nan at step 3"),
    _trial("c", 0, status="stopped", eval__f1=0.20, eval__cd=150.0),
]


def test_means_stds_paper_and_best_by_max():
    table = build_table(OUTCOMES, "eval/f1", "max", "t", "Table 5: teddybear")
    assert table.header == ["cell", "paper setting", "trials", "eval/f1", "paper eval/f1", "eval/cd", "paper eval/cd",
                            "eval/f1/chair"]
    a, b, c = table.rows[:3]
    sd = statistics.stdev([0.40, 0.50])
    assert a == ["a ★", "p", "2/2", f"0.450 ± {sd:.3f}", "0.461", f"75.00 ± {statistics.stdev([80.0, 70.0]):.2f}", "",
                 "0.350 ± 0.071 (0.476)"]
    assert b[:4] == ["b", "", "1/2 (1 failed)", "0.420"]
    assert c[2] == "1/1 (1 stopped)"
    assert table.best == "a"
    assert table.rows[3][:7] == ["baseline: sphere", "", "", "0.107", "", "90.67", ""]
    assert "failed: b · seed 1 — TrainingDiverged: loss became nan at step 3" in table.notes
    assert "paper: Table 5: teddybear" in table.notes


def test_best_by_min_and_all_failed_cell():
    outcomes = OUTCOMES[:4] + [TrialOutcome("d · seed 0", "d", "failed", error="x")]
    table = build_table(outcomes, "eval/cd", "min", "t")
    assert table.best == "b"
    d = next(r for r in table.rows if r[0] == "d")
    assert d[3] == "failed"


def test_markdown_and_csv_written(tmp_path):
    table = build_table(OUTCOMES, "eval/f1", "max", "point_size — profile local")
    md, path = table.write(tmp_path)
    text = md.read_text()
    assert text.startswith("## point_size — profile local\n\n| cell | paper setting | trials | eval/f1 |")
    assert "| a ★ | p | 2/2 |" in text
    rows = list(csv.DictReader(path.open()))
    assert [r["cell"] for r in rows] == ["a", "b", "c", "baseline: sphere"]
    assert float(rows[0]["eval/f1 mean"]) == pytest.approx(0.45)
    assert float(rows[0]["eval/f1 std"]) == pytest.approx(statistics.stdev([0.4, 0.5]))
    assert float(rows[0]["eval/f1 paper"]) == 0.461
    assert rows[1]["failed"] == "1" and rows[0]["best"] == "True"
    assert float(rows[3]["eval/cd mean"]) == pytest.approx(90.6666666)


def _objects(path) -> tuple[dict, ...]:
    text = ("object_id", "category", "eval_set")
    return tuple({k: v if k in text else float(v) for k, v in r.items()} for r in csv.DictReader(path.open()))


def test_a_trained_model_is_marked_better_than_its_reset_copy(tmp_path):
    from cdm.data import build_dataset
    from cdm.diffusion import GaussianDiffusion
    from cdm.evaluate import build_eval_set, run_evaluation
    from cdm.model import CDMNetwork
    from cdm.data.priors2d import PRIOR_2D_CHANNELS
    from cdm.train import fit
    from tests.conftest import tiny_config

    cfg = tiny_config(tmp_path, **{"train.steps": 120, "train.eval_every": 120, "data.val_objects": 6,
                                   "eval.num_objects": 6, "eval.retrieval_bank": 4})
    fit(cfg)
    trained = _objects(tmp_path / "run" / "eval" / "step_0000120" / "objects.csv")
    eval_set = build_eval_set(cfg, build_dataset(cfg, "val"), build_dataset(cfg, "train"), cfg.eval.seed)
    torch.manual_seed(cfg.train.seed)
    reset = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d])
    diffusion = GaussianDiffusion.from_config(cfg.diffusion)
    rows = {}
    for seed in (1234, 99):  # the same untrained model sampled with two seeds
        out = run_evaluation(reset, diffusion, eval_set, cfg.replace(**{"eval.seed": seed}),
                             torch.device("cpu"), None)
        rows[seed] = tuple(out.rows)
    outcomes = [TrialOutcome("reset · seed 0", "reset", "ok", {"eval/cd": 1.0}, objects=rows[1234]),
                TrialOutcome("trained · seed 0", "trained", "ok", {"eval/cd": 1.0}, objects=trained),
                TrialOutcome("reset again · seed 0", "reset again", "ok", {"eval/cd": 1.0}, objects=rows[99])]
    table = build_table(outcomes, "eval/cd", "min", "t")
    verdict = table.header.index("verdict")
    delta = table.records[1]
    assert table.rows[1][verdict] == "better" and delta["eval/cd delta high"] < 0
    assert table.rows[2][verdict] == "no clear difference"
    assert delta["eval/cd delta low"] <= delta["eval/cd delta"] <= delta["eval/cd delta high"]
    assert len({r["eval_set"] for r in trained + rows[99]}) == 1  # the runner pairs only the same evaluation set


def _main_job_outcomes() -> list[TrialOutcome]:
    """The main job's shape (sweeps/point_size.yaml, local profile): 5 cells × 1 seed, 8 categories of 4
    objects, the four baselines, two paper rows; the 0.04 cell scores best and beats only the sphere."""
    categories = ["airplane", "bench", "car", "chair", "lamp", "sofa", "table", "watercraft"]
    baselines = {"sphere": (0.10, 120.0), "gaussian": (0.50, 40.0), "category_mean": (0.55, 35.0), "retrieval": (0.60, 30.0)}
    paper = {0.0075: ("10 frames + 0.0075 point size", 0.451), 0.04: ("10 frames + 0.04 point size", 0.461)}
    out = []
    for size, level in ((0.0075, 0.30), (0.01, 0.31), (0.02, 0.33), (0.04, 0.40), (0.08, 0.35)):
        rows = []
        for i, cat in enumerate(categories * 4):
            wobble = 0.01 * ((i * 7) % 5 - 2)
            row = {"object_id": f"{cat}/{i:04d}", "category": cat, "eval_set": "abc", "f1": level + wobble, "cd": 60.0 - 50 * level}
            for b, (f1, cd) in baselines.items():
                row |= {f"baseline/{b}/f1": f1 + wobble / 2, f"baseline/{b}/cd": cd}
            rows.append(row)
        metrics = {"eval/f1": level, "eval/cd": 60.0 - 50 * level}
        metrics |= {f"eval/{m}/{c}": v + 0.001 for m, v in (("f1", level), ("cd", 60 - 50 * level)) for c in categories}
        metrics |= {f"baseline/{b}/{m}" + suffix: v for b, (f1, cd) in baselines.items() for m, v in (("f1", f1), ("cd", cd))
                    for suffix in ["", *(f"/{c}" for c in categories)]}
        label, value = paper.get(size, (None, None))
        out.append(TrialOutcome(f"point_size={size} · seed 0", f"point_size={size}", "ok", metrics, label,
                                {"eval/f1": value} if value else {}, objects=tuple(rows)))
    return out


def test_terminal_table_fits_120_columns_at_the_main_jobs_size_and_says_where_the_cells_stand():
    table = build_table(_main_job_outcomes(), "eval/f1", "max", "point_size — profile local",
                        "Table 5: Co3D teddybear, F1@0.01; other data sets give other values, compare the trend",
                        settings=["profile local: 800 steps per trial; prediction target x0"])
    text = table.text()
    assert max(len(line) for line in text.splitlines()) <= 120
    assert max(len(line) for line in table.markdown().splitlines()) > 200  # results.md keeps every column
    assert "eval/f1/chair" not in text and "eval/f1/chair" in table.markdown() and "eval/f1/<category>" in text
    assert "not shown here, in results.md and results.csv: " in text
    assert "best cell point_size=0.04: beats sphere; below Gaussian, category mean, retrieval" in text
    assert "cells point_size=0.0075, point_size=0.01, point_size=0.02, point_size=0.08: beat sphere; below Gaussian" in text
    # Footnotes only when they apply: one seed (no ±), no per-category paper numbers.
    assert "±" not in text and "ours (paper)" not in text
    # Baselines are reference rows: numbers, no Δ or verdict against the reference cell.
    baseline = next(r for r in table.rows if r[0] == "baseline: retrieval")
    for column in ("verdict", "Δf1 vs point_size=0.0075 [95% CI]", "beats baselines"):
        assert baseline[table.header.index(column)] == ""
    assert table.rows[3][table.header.index("verdict")] == "better"
    assert table.records[-1]["eval/f1 mean"] == pytest.approx(0.60)


def test_settings_note_says_lambda_and_where_it_was_set():
    note = settings_note("local", 800, ["x0"], [0.1, 0.1], "profile local")
    assert note == ("profile local: 800 steps per trial; prediction target x0; "
                    "λ (priors.lambda_3d, Eq. 6) 0.1, from profile local, not from the paper")
    assert "λ (priors.lambda_3d, Eq. 6) per cell (0.01, 1)," in settings_note("local", 800, ["x0"], [1.0, 0.01], "the spec's cells")
    assert "λ (priors.lambda_3d, Eq. 6) searched," in settings_note("local", 800, ["x0"], [], "the spec's search")
