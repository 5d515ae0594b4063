"""Results table: mean ± std over seeds, the paper's number beside it, best cell, baselines, failures."""

from __future__ import annotations

import csv
import statistics

import pytest

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
