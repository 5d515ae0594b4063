"""Results table: mean ± std over seeds, the paper's number beside it, best cell, baselines, failures."""

from __future__ import annotations

import csv
import statistics
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cdm.metric_names import label as metric_label
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.rules import machine_note, settings_note, settings_notes
from sweeps.compare.sequential import Decision, SeedInterval, SettleRecord
from sweeps.compare.table import build_table
from sweeps.plan.spec import load_spec

SWEEPS = Path(__file__).resolve().parent.parent / "sweeps"


def _trial(cell, seed, status="ok", **metrics):
    return TrialOutcome(
        f"{cell} · seed {seed}",
        cell,
        status,
        {k.replace("__", "/"): v for k, v in metrics.items()},
        paper_label="p" if cell == "a" else None,
        paper={"eval/f1": 0.461, "eval/f1/chair": 0.476} if cell == "a" else {},
    )


OUTCOMES = [
    _trial(
        "a", 0, eval__f1=0.40, eval__cd=80.0, eval__f1__chair=0.30, baseline__sphere__f1=0.10, baseline__sphere__cd=90.0
    ),
    _trial(
        "a", 1, eval__f1=0.50, eval__cd=70.0, eval__f1__chair=0.40, baseline__sphere__f1=0.12, baseline__sphere__cd=92.0
    ),
    _trial(
        "b", 0, eval__f1=0.42, eval__cd=60.0, eval__f1__chair=0.20, baseline__sphere__f1=0.10, baseline__sphere__cd=90.0
    ),
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


@pytest.mark.slow
def test_a_trained_model_is_marked_better_than_its_reset_copy(tmp_path):
    from cdm.data import build_dataset
    from cdm.data.priors2d import PRIOR_2D_CHANNELS
    from cdm.diffusion import GaussianDiffusion
    from cdm.evaluate import build_eval_set, run_evaluation
    from cdm.model import CDMNetwork
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
    baselines = {
        "sphere": (0.10, 120.0),
        "gaussian": (0.50, 40.0),
        "category_mean": (0.55, 35.0),
        "retrieval": (0.60, 30.0),
    }
    paper = {0.0075: ("10 frames + 0.0075 point size", 0.451), 0.04: ("10 frames + 0.04 point size", 0.461)}
    out = []
    for size, level in ((0.0075, 0.30), (0.01, 0.31), (0.02, 0.33), (0.04, 0.40), (0.08, 0.35)):
        rows = []
        for i, cat in enumerate(categories * 4):
            wobble = 0.01 * ((i * 7) % 5 - 2)
            row = {
                "object_id": f"{cat}/{i:04d}",
                "category": cat,
                "eval_set": "abc",
                "f1": level + wobble,
                "cd": 60.0 - 50 * level,
            }
            for b, (f1, cd) in baselines.items():
                row |= {f"baseline/{b}/f1": f1 + wobble / 2, f"baseline/{b}/cd": cd}
            rows.append(row)
        metrics = {"eval/f1": level, "eval/cd": 60.0 - 50 * level}
        metrics |= {f"eval/{m}/{c}": v + 0.001 for m, v in (("f1", level), ("cd", 60 - 50 * level)) for c in categories}
        metrics |= {
            f"baseline/{b}/{m}" + suffix: v
            for b, (f1, cd) in baselines.items()
            for m, v in (("f1", f1), ("cd", cd))
            for suffix in ["", *(f"/{c}" for c in categories)]
        }
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
    assert (
        "best cell point_size=0.04 (Δf1 +0.050 [+0.050, +0.050] against the next cell): beats sphere; below Gaussian, "
        "category mean, retrieval"
    ) in " ".join(text.split())
    assert (
        "cells point_size=0.0075, point_size=0.01, point_size=0.02, point_size=0.08: beat sphere; below Gaussian"
        in text
    )
    # Footnotes only when they apply: one seed (no ±), no per-category paper numbers.
    assert "±" not in text and "ours (paper)" not in text
    # Baselines are reference rows: numbers, no Δ or verdict against the reference cell.
    baseline = next(r for r in table.rows if r[0] == "baseline: retrieval")
    for column in ("verdict", "Δf1 vs point_size=0.0075 [95% CI]", "beats baselines"):
        assert baseline[table.header.index(column)] == ""
    assert table.rows[3][table.header.index("verdict")] == "better"
    assert table.records[-1]["eval/f1 mean"] == pytest.approx(0.60)


SHIPPED_SPECS = sorted(p for p in SWEEPS.glob("*.yaml") if p.name != "profiles.yaml")


@pytest.mark.parametrize("path", SHIPPED_SPECS, ids=lambda p: p.stem)
def test_every_printed_line_fits_120_columns_for_each_shipped_specs_cells_and_metric(path):
    """The main job's shape (sweeps/point_size.yaml) and every other spec's: its longest cell names (up to 38
    characters, prior_type.yaml), its metric, the paper rows, the driver's notes; each line as wide as a
    terminal shows it (★ and Δ one column each, three and two bytes in UTF-8)."""
    from dataclasses import replace

    from sweeps.compare.rules import PROTOCOL_NOTE
    from sweeps.compare.table import display_width
    from sweeps.plan.trials import expand

    spec = load_spec(path)
    names = [c.name for c in expand(spec, "local", {}).cells] if spec.grid or spec.cells else []
    searched = [f"priors.lambda_3d={v:g}" for v in (0.0316228, 0.00177828)]  # lambda.yaml: an Optuna search
    names = sorted(dict.fromkeys(names), key=len, reverse=True)[:5] or searched
    outcomes = [replace(o, label=f"{name} · seed 0", cell=name)
                for o, name in zip(_main_job_outcomes(), names * 5)]
    paper = f"{spec.paper.table}: {spec.paper.note}" if spec.paper else ""
    table = build_table(outcomes, spec.metric.name, spec.metric.mode, f"{spec.name} — profile local", paper,
                        settings=["profile local: 1400 steps per trial; prediction target x0; λ (priors.lambda_3d, "
                                  "Eq. 6) 0.1, from profile local, not from the paper"])
    printed = replace(table, notes=[n for n in table.notes if not n.startswith(PROTOCOL_NOTE)]
                      + ["protocol card: printed above, and in results.md"]).text()
    widest = max(printed.splitlines(), key=display_width)
    assert display_width(widest) <= 120, widest
    assert all(len(line.encode()) <= 120 for line in printed.splitlines())  # columns in any terminal
    header = printed.split("\n---", 1)[0].split("\n---", 1)[0]
    assert "verdict" in header and "[95% CI]" in header  # the answer's columns stay in the terminal's table


def test_display_width_counts_terminal_columns_not_bytes():
    from sweeps.compare.table import display_width

    assert display_width("point_size=0.04 ★") == 17 and len("point_size=0.04 ★".encode()) == 19
    assert display_width("Δf1 ±") == 5 and display_width("表") == 2 and display_width("e\u0301") == 1


def test_the_results_table_reads_the_baselines_names_without_torch_or_the_model():
    code = "import sys, sweeps.compare.table; print(sorted(m for m in ('torch', 'cdm.evaluate') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=SWEEPS.parent)
    assert out.stdout.strip() == "[]"


def test_settings_note_says_lambda_and_where_it_was_set():
    note = settings_note("local", 800, ["x0"], [0.1, 0.1], "profile local")
    assert note == ("profile local: 800 steps per trial; prediction target x0; "
                    "λ (priors.lambda_3d, Eq. 6) 0.1, from profile local, not from the paper")
    assert "λ (priors.lambda_3d, Eq. 6) per cell (0.01, 1)," in settings_note(
        "local", 800, ["x0"], [1.0, 0.01], "the spec's cells"
    )
    assert "λ (priors.lambda_3d, Eq. 6) searched," in settings_note("local", 800, ["x0"], [], "the spec's search")


def test_settings_notes_without_trials_resolve_the_fixed_settings_and_sets_as_a_trial_would():
    """The runner before a sampled search's trials and the report of trials that recorded nothing use one rule:
    the plan's fixed overrides and --set values resolved by load_config (not the config's defaults by hand)."""
    spec = load_spec(SWEEPS / "point_size.yaml")
    fixed = {"diffusion.prediction": "x0", "priors.lambda_3d": 0.1}
    note, card = settings_notes(spec, "local", 1400, fixed, {}, ["a line"])
    assert note == ("profile local: 1400 steps per trial; prediction target x0; "
                    "λ (priors.lambda_3d, Eq. 6) 0.1, from profile local, not from the paper")
    assert card == "protocol: a line"
    note = settings_notes(spec, "smoke", 20, {}, {"priors.lambda_3d": 0.5}, [])[0]
    assert "prediction target eps; λ (priors.lambda_3d, Eq. 6) 0.5, from --set" in note
    note = settings_notes(spec, "local", 1400, fixed, {}, [], [("v", 0.2), ("x0", 0.2)])[0]
    assert "prediction target per cell (v, x0); λ (priors.lambda_3d, Eq. 6) 0.2, from profile local" in note


XEON = {"repro.cpu_model": "Intel(R) Xeon(R) Processor", "repro.cpu_isa": "avx2 avx512f amx_tile",
        "repro.cpu_capability": "AVX512", "repro.math_libraries": "BLAS mkl, MKL 2024.2 build 20240605",
        "repro.kernel_pins": "none", "repro.packages_digest": "aced6566623b66f8"}


def test_the_machine_note_names_the_trials_machine_or_each_of_them():
    xeon = ("Intel(R) Xeon(R) Processor (avx2 avx512f amx_tile), ATen AVX512, BLAS mkl, MKL 2024.2 build 20240605, "
            "kernel pins none, packages aced6566623b66f8")
    where = " (every package: each child run's environment/packages.txt)"
    assert machine_note([XEON, XEON, {"seed": "0"}]) == f"machine: {xeon}{where}"
    epyc = {**XEON, "repro.cpu_model": "AMD EPYC 7B13\n- planted note", "repro.cpu_isa": "avx2",
            "repro.cpu_capability": "AVX2"}
    assert machine_note([epyc, XEON, XEON]) == (
        f"machines differ between trials, and so may their numbers: 2 on {xeon}; 1 on AMD EPYC 7B13 - planted note "
        "(avx2), ATen AVX2, BLAS mkl, MKL 2024.2 build 20240605, kernel pins none, packages aced6566623b66f8" + where)
    assert machine_note([{"seed": "0"}]) == "machine: not recorded (trials from before the record named it)"
    spec = load_spec(SWEEPS / "point_size.yaml")
    notes = settings_notes(spec, "local", 1400, {}, {}, ["a line"], machines=[XEON])
    assert notes[1] == f"machine: {xeon}{where}" and notes[2] == "protocol: a line"


REF_F1 = [0.40, 0.50, 0.30, 0.45, 0.35, 0.50]
REF_CD = [50.0, 40.0, 60.0, 45.0, 55.0, 40.0]
WOBBLE = [1, -1, 0.5, -0.5, 1, -1]  # sums to 0: a shift by it alone leaves the mean where it was


def _scored(cell: str, f1: list[float], cd: list[float], seed: int = 0) -> TrialOutcome:
    """A trial with per-object rows on 6 chairs; the sphere scores far worse, the Gaussian worse F1, better CD."""
    baselines = {"sphere": (0.10, 100.0), "gaussian": (0.10, 10.0)}
    rows = tuple(
        {"object_id": f"o{i}", "category": "chair", "f1": f, "cd": c}
        | {f"baseline/{b}/{m}": v + w / 100 for b, (bf, bc) in baselines.items() for m, v in (("f1", bf), ("cd", bc))}
        for i, (f, c, w) in enumerate(zip(f1, cd, WOBBLE))
    )
    metrics = {"eval/f1": statistics.fmean(f1), "eval/cd": statistics.fmean(cd)}
    metrics |= {f"baseline/{b}/{m}": v for b, (bf, bc) in baselines.items() for m, v in (("f1", bf), ("cd", bc))}
    return TrialOutcome(f"{cell} · seed {seed}", cell, "ok", metrics, objects=rows)


def _weighing_outcomes() -> list[TrialOutcome]:
    """``trade``: F1 up 0.05, CD worse by 5; ``cd only``: F1 only wobbles (Δ 0), CD worse by 3."""
    return [
        _scored("ref", REF_F1, REF_CD),
        _scored(
            "trade", [f + 0.05 + w / 100 for f, w in zip(REF_F1, WOBBLE)], [c + 5 + w for c, w in zip(REF_CD, WOBBLE)]
        ),
        _scored("cd only", [f + w / 50 for f, w in zip(REF_F1, WOBBLE)], [c + 3 + w for c, w in zip(REF_CD, WOBBLE)]),
    ]


def test_the_verdict_weighs_the_partner_metric():
    table = build_table(_weighing_outcomes(), "eval/f1", "max", "t")
    verdict = {r[0].removesuffix(" ★"): r[table.header.index("verdict")] for r in table.rows}
    assert verdict["trade"] == "better on f1, worse on cd"
    assert verdict["cd only"] == "worse on cd"  # F1's interval holds 0; CD's does not: never "no clear difference"
    assert verdict["ref"] == ""
    assert [r["verdict"] for r in table.records[:3]] == ["", "better on f1, worse on cd", "worse on cd"]
    text = table.text()
    assert "no clear difference" not in text and "level with" not in text
    # Against the Gaussian every cell scores better F1 and worse CD: that is what the sentence says.
    assert (
        "best cell trade (Δf1 +0.050 [+0.043, +0.057] against the next cell): beats sphere; better on f1, worse on cd "
        "than Gaussian"
    ) in table.summary
    assert "against ref: trade better on f1, worse on cd; cd only worse on cd" in table.summary
    assert [r["beats baselines"] for r in table.records[:3]] == ["sphere"] * 3
    assert "verdict and beats baselines by eval/f1 (max) and eval/cd (min)" in text


def test_the_star_needs_a_difference_the_table_prints():
    # The main job's 0.08 over 0.04 by 1.2e-6 in F1: both print 0.468.
    close = [_trial("a", 0, eval__f1=0.4680004, eval__cd=50.0), _trial("b", 0, eval__f1=0.4680016, eval__cd=51.0),
             _trial("c", 0, eval__f1=0.30, eval__cd=70.0)]
    table = build_table(close, "eval/f1", "max", "t")
    assert table.best is None and [r[0] for r in table.rows] == ["a (tied)", "b (tied)", "c"]
    assert "no ★: b, a tied for best by eval/f1 (max) at the printed precision" in table.notes
    assert table.summary[0] == "no best cell: b, a tie at eval/f1 0.468"
    apart = build_table(close[:1] + [_trial("b", 0, eval__f1=0.469, eval__cd=51.0)], "eval/f1", "max", "t")
    assert (
        apart.best == "b"
        and apart.rows[1][0] == "b ★"
        and apart.notes[-1].startswith("★ highest mean eval/f1 (max), apart")
    )
    # Without per-object scores nothing tells the leader apart from the next cell: no "best".
    assert (
        apart.summary[0]
        == "no cell is resolvably best by eval/f1: the leader b (unpaired with the next cell): eval/f1 0.469"
    )


def test_best_only_where_the_leaders_interval_against_the_next_cell_excludes_0():
    # `close` leads `ref` by 0.002 in F1 with a wobble of ±0.01 per object: starred, but not resolvably best.
    close = [
        _scored("ref", REF_F1, REF_CD),
        _scored("close", [f + 0.002 + w / 100 for f, w in zip(REF_F1, WOBBLE)], REF_CD),
    ]
    table = build_table(close, "eval/f1", "max", "t")
    assert table.best == "close" and table.rows[1][0] == "close ★"
    assert table.summary[0].startswith("no cell is resolvably best by eval/f1: the leader close (Δf1 +0.002 [")
    assert table.summary[0].endswith("against the next cell): beats sphere; better on f1, worse on cd than Gaussian")
    assert not any(s.startswith("best cell") for s in table.summary)


def test_the_notes_say_what_the_intervals_cover():
    one = build_table(_weighing_outcomes(), "eval/f1", "max", "t").notes
    assert ("the bootstrap intervals cover the held-out objects only, not training seeds: with one seed per cell, "
            "another seed can move a cell by more than an interval's width") in one
    two = build_table(_weighing_outcomes() + [_scored("ref", REF_F1, REF_CD, seed=1)], "eval/f1", "max", "t").notes
    assert ("the bootstrap intervals cover the held-out objects only, not training seeds: the seeds are averaged, "
            "their spread is not in the interval") in two


def test_settled_cells_show_their_seeds_interval_and_verdict(tmp_path):
    from sweeps.compare.sequential import FOOTNOTE, Decision, SeedInterval, SettleRecord

    settled = {"trade": SettleRecord(2, Decision(SeedInterval(0.05, 0.02, 0.08, 2, 6, "seeds and objects"), "better"),
                                     "settled"),
               "cd only": SettleRecord(5, Decision(SeedInterval(0.0, -0.03, 0.03, 5, 6, "seeds and objects"), "open"),
                                       "max")}
    plain = build_table(_weighing_outcomes(), "eval/f1", "max", "t")
    table = build_table(_weighing_outcomes(), "eval/f1", "max", "t", settled=settled)
    assert table.header == plain.header[:2] + ["seeds"] + plain.header[2:]
    rows = {r[0].removesuffix(" ★"): dict(zip(table.header, r)) for r in table.rows}
    assert (rows["trade"]["seeds"], rows["cd only"]["seeds"], rows["ref"]["seeds"]) == ("2 (settled)", "5 (max)", "")
    assert rows["trade"]["Δf1 vs ref [95% CI]"] == "+0.050 [+0.020, +0.080]"
    assert rows["trade"]["Δcd vs ref [95% CI]"] == plain.rows[1][plain.header.index("Δcd vs ref [95% CI]")]
    assert rows["trade"]["verdict"] == "better, settled after 2 seeds (worse on cd, objects only)"
    assert rows["cd only"]["verdict"] == "open at 5 seeds (worse on cd, objects only)"
    assert rows["baseline: sphere"]["seeds"] == ""
    assert FOOTNOTE in table.notes and FOOTNOTE not in plain.notes
    assert table.answer[:2] == ("cell", "seeds")
    _, path = table.write(tmp_path)
    trade = next(r for r in csv.DictReader(path.open()) if r["cell"] == "trade")
    assert (trade["seeds"], trade["stop reason"], trade["eval/f1 delta covers"]) == (
        "2",
        "settled",
        "seeds and objects",
    )
    assert float(trade["eval/f1 delta low"]) == 0.02
    assert "against ref: trade better, settled after 2 seeds (worse on cd, objects only); cd only open at 5 seeds " \
           "(worse on cd, objects only)" in table.summary


def test_every_f1_label_names_its_threshold_in_world_units():
    table = build_table(_main_job_outcomes(), "eval/f1", "max", "point_size — profile local")
    for text in (table.text(), table.markdown()):
        assert (
            "F1 is F1@0.01 on the squared distance: a point counts when it lies within 0.1 in world units"
            in " ".join(text.split())
        )
    assert metric_label("eval/f1", 0.01) == "eval/f1 (F1@0.01 sq. dist = 0.1 world)"
    assert (
        metric_label("eval/f1/chair", 0.01).endswith("(F1@0.01 sq. dist = 0.1 world)")
        and metric_label("eval/cd", 0.01) == "eval/cd (CD ×1000)"
    )
    assert metric_label("train/loss", 0.01) == "train/loss"
    no_f1 = build_table([_trial("a", 0, train__loss=0.5)], "train/loss", "min", "t")  # no F1 shown: no footnote
    assert not any(n.startswith("F1 is") for n in no_f1.notes)


SEED_SHIFTS = (0.30, -0.25, 0.10)
"""What each training seed adds to ``b`` over ``a``: the seeds disagree far more than the objects do."""


def _seeded_outcomes(seeds: int = 3) -> list[TrialOutcome]:
    out = []
    for seed, shift in enumerate(SEED_SHIFTS[:seeds]):
        out += [_scored("a", REF_F1, REF_CD, seed),
                _scored("b", [f + shift + w / 100 for f, w in zip(REF_F1, WOBBLE)], REF_CD, seed)]
    return out


def test_where_seeds_vary_the_headline_and_the_rows_use_the_seeds_by_objects_interval():
    table = build_table(_seeded_outcomes(), "eval/f1", "max", "t")
    rows = {r[0].removesuffix(" ★"): dict(zip(table.header, r)) for r in table.rows}
    # Seeds averaged per object, b leads a by 0.05 on every object: the objects-only interval is narrow and
    # excludes 0, but the three seeds disagree (+0.30, −0.25, +0.10): over seeds and objects it holds 0.
    assert table.best == "b"
    assert table.summary[0].startswith("no cell is resolvably best by eval/f1: the leader b (Δf1 +0.050 [")
    assert "against the next cell, over seeds and objects" in table.summary[0]
    low, high = (float(v) for v in rows["b"]["Δf1 vs a [95% CI]"].split("[")[1].rstrip("]").split(", "))
    assert low < 0 < high and high - low > 0.5  # the row's interval, the headline's
    assert f"[{low:+.3f}, {high:+.3f}]" in table.summary[0]
    assert rows["b"]["verdict"] == "no clear difference"
    assert table.records[1]["eval/f1 delta covers"] == "seeds and objects"
    assert any(n.startswith("seeds vary: Δf1 and its verdict") for n in table.notes)
    assert any("its interval over seeds and objects (as the verdicts') against the next cell" in n for n in table.notes)
    # A sequential sweep's settled rows: the headline spends the same share of 5 % as they do (4 looks).
    from sweeps.compare.sequential import decide

    per_seed = {c: {int(o.label[-1]): {r["object_id"]: r["f1"] for r in o.objects} for o in _seeded_outcomes()
                    if o.cell == c} for c in "ab"}
    decision = decide(per_seed["b"], per_seed["a"], mode="max", margin=None, look=2, looks=4)
    settled = build_table(_seeded_outcomes(), "eval/f1", "max", "t",
                          settled={"b": SettleRecord(3, decision, "max", looks=4)})
    srow = dict(zip(settled.header, settled.rows[1]))
    # At 3 seeds and four looks the interval, [−1.37, +1.47], is wider than F1 allows: cut, and said so.
    assert (decision.interval.low, decision.interval.high) == pytest.approx((-1.374154, 1.474154))
    assert (srow["Δf1 vs a [95% CI]"], srow["verdict"]) == ("+0.050 [-1.000, +1.000]", "too few objects to tell")
    assert settled.summary[0] == (
        "no cell is resolvably best by eval/f1: the leader b (Δf1 +0.050 [-1.000, +1.000] against the next cell, "
        "over seeds and objects, too few objects to tell): beats sphere; better on f1, worse on cd than Gaussian")


def test_one_seed_per_cell_keeps_the_objects_only_interval():
    table = build_table(_seeded_outcomes(seeds=1), "eval/f1", "max", "t")
    assert table.summary[0].startswith("best cell b (Δf1 +0.300 [") and "over seeds" not in table.summary[0]
    assert table.records[1]["eval/f1 delta covers"] == "objects"


def test_an_interval_wider_than_f1_can_be_is_cut_to_its_range_and_says_too_few_objects(tmp_path):
    # Two seeds of a smoke sweep, seeds × objects at t₁: an F1 interval like [−3.47, +3.67].
    wide = SettleRecord(3, Decision(SeedInterval(0.1, -3.47, 3.67, 3, 6, "seeds and objects"), "open"), "max", looks=4)
    table = build_table(_weighing_outcomes()[:2], "eval/f1", "max", "t", settled={"trade": wide})
    row = dict(zip(table.header, next(r for r in table.rows if r[0].startswith("trade"))))
    assert row["Δf1 vs ref [95% CI]"] == "+0.100 [-1.000, +1.000]"
    assert row["verdict"] == "too few objects to tell (worse on cd, objects only)"
    assert ('Δf1 intervals reaching past [-1, +1] (F1 lies in [0, 1]) are cut to it; where one still holds 0 the '
            'verdict says "too few objects to tell"') in table.notes
    assert max(len(line.encode()) for line in table.text().splitlines()) <= 120
    _, path = table.write(tmp_path)
    record = next(r for r in csv.DictReader(path.open()) if r["cell"] == "trade")
    assert (float(record["eval/f1 delta low"]), float(record["eval/f1 delta high"])) == (-1.0, 1.0)
    # Cut but still clear of 0: the data tell, the verdict stands.
    sure = SettleRecord(3, Decision(SeedInterval(0.6, 0.2, 1.3, 3, 6, "seeds and objects"), "better"), "settled")
    row = build_table(_weighing_outcomes()[:2], "eval/f1", "max", "t", settled={"trade": sure}).records[1]
    assert row["eval/f1 delta high"] == 1.0
    assert row["verdict"] == "better, settled after 3 seeds (worse on cd, objects only)"
    # CD's Δ has no bound that holds whatever the reference's true mean: never cut.
    cd_wide = SettleRecord(3, Decision(SeedInterval(3.0, -900.0, 900.0, 3, 6, "seeds and objects"), "open"), "max")
    by_cd = build_table(_weighing_outcomes(), "eval/cd", "min", "t", settled={"cd only": cd_wide})
    row = dict(zip(by_cd.header, next(r for r in by_cd.rows if r[0].startswith("cd only"))))
    assert row["Δcd vs ref [95% CI]"] == "+3.00 [-900.00, +900.00]" and "too few" not in row["verdict"]


def test_the_cost_column_is_each_cells_measured_compute_mean_over_its_finished_seeds(tmp_path):
    # Seeds of a cell cost what each measured (a budget of 190 s is spent to a step's grain, or not at all when
    # ASHA stopped it): the column is their mean, a failed trial's report left out, a cell without one "–".
    trials = [_trial("a", 0, eval__f1=0.5, eval__cd=40.0, train__compute_s=190.4),
              _trial("a", 1, eval__f1=0.6, eval__cd=41.0, train__compute_s=191.0),
              _trial("b", 0, eval__f1=0.4, eval__cd=45.0, train__compute_s=95.2),
              _trial("b", 1, "failed", train__compute_s=12.0),
              _trial("c", 0, eval__f1=0.3, eval__cd=50.0)]
    table = build_table(trials, "eval/f1", "max", "t")
    cost = table.header.index("compute s")
    assert table.header[cost - 1] == "trials"
    assert [r[cost] for r in table.rows[:3]] == ["190.7", "95.2", "–"]
    records = {r["cell"]: r for r in table.records}
    assert records["a"]["train/compute_s mean"] == pytest.approx(190.7)
    assert records["b"]["train/compute_s mean"] == 95.2 and records["c"]["train/compute_s mean"] is None
    assert any(n.startswith("compute s: each cell's measured cost") and "CPU seconds" in n for n in table.notes)
    _, written = table.write(tmp_path)
    rows = list(csv.DictReader(written.open()))
    assert [r["train/compute_s mean"] for r in rows[:3]] == ["190.7", "95.2", ""]
    # Trials that report no compute (sweeps from before it) keep their table as it was.
    assert "compute s" not in build_table(trials[4:], "eval/f1", "max", "t").header


def test_a_budget_in_compute_says_its_unit_in_the_tables_first_note():
    note = settings_note("local", 4000, ["x0"], [], "the spec's search", compute_s="190.0")
    assert note.startswith("profile local: 190 s of compute (at most 4000 steps) per trial;")
