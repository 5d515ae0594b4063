"""Results table: mean ± std over seeds, the paper's number beside it, best cell, baselines, failures."""

from __future__ import annotations

import csv
import statistics

import pytest
import torch

from sweeps.results import TrialOutcome, build_table


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
