"""Sweep specs: every shipped spec expands, resolution order holds, bad specs fail before Ray with code 2."""

from __future__ import annotations

from pathlib import Path

import pytest

from cdm.config import Config, ConfigError
from sweeps import run
from sweeps.compare.rules import lambda_source
from sweeps.plan.budget import SeedBudget, parse_budget
from sweeps.plan.estimate import Estimate
from sweeps.plan.profiles import Resources, load_profiles
from sweeps.plan.resources import plan_concurrency
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import Spec, load_spec
from sweeps.plan.trials import expand
from tests.input_fixtures import object_ids, paper_inputs, write_condition_images, write_embeddings

SWEEPS = Path(__file__).resolve().parent.parent / "sweeps"
SHIPPED = sorted(p for p in SWEEPS.glob("*.yaml") if p.name != "profiles.yaml")
NEEDS_INPUTS = [p for p in SHIPPED if "$CDM_INPUTS" in p.read_text()]  # Tables 7 and 8: embeddings, generated images

EXPECTED_TRIALS = {  # cells × seeds per shipped spec (Optuna: num_samples of the profile)
    "point_size": 5,
    "frames": 7,
    "frames_point_size": 3,
    "priors_2d_3d": 4,
    "prior_type": 6,
    "global_features": 6,
    "conditions": 7,
    "prediction": 3,
    "bdm_blend": 20,
    "shapenet": 10,
    "co3d": 6,
    "lambda": {"smoke": 4, "local": 8, "paper": 32},
    "local_recipe": {"smoke": 4, "local": 24, "paper": 64},
    "local_recipe_check": {"smoke": 4, "local": 4, "paper": 4},
}


def test_the_specs_of_the_issues_are_shipped():
    assert {p.stem for p in SHIPPED} == set(EXPECTED_TRIALS)
    assert {p.stem for p in NEEDS_INPUTS} == {"global_features", "conditions"}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """``$CDM_INPUTS`` for the specs that read it: OpenCLIP-like embeddings and generated condition images
    for every object of every profile. The smoke objects get all views at the smoke image size (the
    estimate's calibration trains on them); the other profiles' only round 0's input view, 8 px (a dry
    run checks that each object has its entry, and reads no image)."""
    folder = tmp_path_factory.mktemp("inputs")
    baseline = {
        p: expand(load_spec(SWEEPS / "conditions.yaml"), p).cells[0].config for p in ("smoke", "local", "paper")
    }
    smoke = object_ids(baseline["smoke"])
    ids = sorted({o for cfg in baseline.values() for o in object_ids(cfg)})
    for seed, kind in enumerate(("text", "image", "depth")):
        write_embeddings(folder / "openclip" / f"{kind}.npz", ids, (16,), seed)
    write_condition_images(folder / "controlnet", smoke, views=3, size=baseline["smoke"].data.image_size)
    write_condition_images(folder / "controlnet", sorted(set(ids) - set(smoke)), views=0, size=8)
    return paper_inputs(folder)


@pytest.fixture
def given_inputs(path, request, monkeypatch):
    """Point ``$CDM_INPUTS`` at the written inputs when the test's spec or profile reads them."""
    if path in NEEDS_INPUTS or request.node.callspec.params.get("profile") == "paper":
        monkeypatch.setenv("CDM_INPUTS", str(request.getfixturevalue("inputs")))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
@pytest.mark.parametrize("profile", ["smoke", "local", "paper"])
def test_every_shipped_spec_expands_in_every_profile(path, profile):
    plan = expand(load_spec(path), profile)
    want = EXPECTED_TRIALS[path.stem]
    assert plan.num_trials == (want[profile] if isinstance(want, dict) else want)
    assert len({c.label for c in plan.cells}) == len(plan.cells)
    for cell in plan.cells:
        assert cell.config.train.steps == plan.profile.steps
        for key, value in cell.values.items():
            assert cell.config.flat()[key] == (list(value) if isinstance(value, (list, tuple)) else value)


@pytest.mark.slow  # each estimate trains a few calibration steps: 3-9 s a spec, ~45 s together
@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_dry_run_lists_every_trial_estimates_its_cost_and_writes_nothing(
    path, given_inputs, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    assert run.main([str(path), "--dry-run", "--smoke"]) == 0  # smoke: the calibration takes a second
    out = capsys.readouterr().out
    plan = expand(load_spec(path), "smoke")
    for cell in plan.cells:
        assert cell.label in out
    for key in plan.spec.search.space:
        assert key in out
    assert "concurrent trials" in out and "profile smoke" in out
    estimate = next(line for line in out.splitlines() if line.startswith("estimate:"))
    assert f"{plan.num_trials} trials ×" in estimate and "min wall on this machine" in estimate
    # The paper profile trains PC²'s PVCNN2, whose GPU step no session has measured: no figure, and why.
    # The estimate may fold over lines (asha's expected time); the paper-profile line comes right after it.
    after_estimate = out[out.index(estimate):].split("\n  paper-profile GPU-hours:", 1)
    assert "\n" not in after_estimate[0].replace("\n  ", " ") and len(after_estimate) == 2
    assert after_estimate[1].startswith(" not measured for model.denoiser=pvcnn2")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
@pytest.mark.parametrize("profile", ["smoke", "local", "paper"])
def test_every_spec_dry_runs_in_every_profile_with_its_protocol_card(
    path, profile, given_inputs, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    assert run.main([str(path), "--dry-run", "--no-estimate", "--profile", profile]) == 0
    out = capsys.readouterr().out
    card = out.split("protocol card:\n", 1)[1].splitlines()
    assert card[0].startswith("  deviation: data set: the procedural data set stands in")  # no data.root given
    assert f"profile {profile}" in out and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("path", "field"),
    [
        (SWEEPS / "global_features.yaml", "model.global_embeddings"),
        (SWEEPS / "conditions.yaml", "data.condition_folder"),
    ],
    ids=lambda v: getattr(v, "stem", v),
)
def test_a_dry_run_without_the_external_inputs_exits_2_naming_the_field(path, field, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("CDM_INPUTS", raising=False)
    assert run.main([str(path), "--dry-run", "--smoke"]) == 2
    captured = capsys.readouterr()
    assert f"{field}=$CDM_INPUTS/" in captured.out and "(MISSING)" in captured.out
    error = captured.err.strip().splitlines()[-1]
    assert error.startswith(f"error: {field}: $CDM_INPUTS/") and "set the environment variable it names" in error
    assert list(tmp_path.iterdir()) == []


def test_profiles_differ_in_size_and_the_paper_profile_has_the_paper_settings():
    spec = load_spec(SWEEPS / "shapenet.yaml")  # Table 1: ShapeNet sizes (Table 5's point_size.yaml is Co3D's)
    smoke, local, paper = (expand(spec, p).cells[0].config for p in ("smoke", "local", "paper"))
    assert smoke.data.image_size < local.data.image_size < paper.data.image_size == 224
    assert (paper.data.num_points, paper.train.batch_size, paper.train.steps) == (4096, 8, 100_000)
    assert paper.diffusion.prediction == "eps"
    co3d = expand(load_spec(SWEEPS / "priors_2d_3d.yaml"), "paper").cells[0].config
    assert co3d.data.num_points == 16384  # the spec's own patch of the paper profile


SHARED = load_profiles()


def _spec(**fields) -> Spec:
    return Spec.model_validate({"name": "t", **fields})


def test_resolution_order_profile_base_spec_profile_budget_cell_seed_set():
    shared = {"p": SHARED["smoke"]}
    spec = _spec(
        base={"priors.lambda_3d": 0.5, "train.lr": 0.01, "eval.num_objects": 3},
        grid={"priors.point_size": [0.02, 0.04]},
        seeds=[3, 4],
        profiles={"p": {"overrides": {"train.lr": 0.02}, "budget": {"steps": 7}}},
    )
    plan = expand(spec, "p", {"eval.num_objects": 2}, shared=shared)
    assert [c.label for c in plan.cells] == [
        "point_size=0.02 · seed 3", "point_size=0.02 · seed 4", "point_size=0.04 · seed 3", "point_size=0.04 · seed 4"]
    cfg = plan.cells[3].config
    assert cfg.data.image_size == 32  # shared profile
    assert cfg.priors.lambda_3d == 0.5  # spec base
    assert cfg.train.lr == 0.02  # spec profile beats base
    assert (cfg.train.steps, cfg.train.eval_every) == (7, 10)  # budget patched, eval_every inherited
    assert cfg.priors.point_size == 0.04 and cfg.train.seed == 4  # cell and seed
    assert cfg.eval.num_objects == 2  # --set wins
    assert cfg.train.threads == 1  # = CPUs per worker


def test_a_trials_f1_threshold_is_what_it_drew_else_its_cells_else_the_plans():
    shared = {"p": SHARED["smoke"]}
    spec = _spec(grid={"eval.f1_threshold": [0.02, 0.04]}, seeds=[3])
    plan = expand(spec, "p", {}, shared=shared)
    assert [plan.f1_threshold(c.label, {}) for c in plan.cells] == [0.02, 0.04]
    assert plan.f1_threshold(plan.cells[0].label, {"eval.f1_threshold": "0.5"}) == 0.5  # a run's logged param
    assert plan.f1_threshold("no such cell · seed 3", {}) == Config().eval.f1_threshold == 0.01
    spec = _spec(base={"eval.f1_threshold": 0.03}, grid={"train.lr": [0.01]}, seeds=[3])
    fixed = expand(spec, "p", {}, shared=shared)
    assert fixed.f1_threshold("sampled · seed 3", {}) == 0.03


def test_a_budget_left_out_is_the_configs_default_the_papers_length():
    """The paper profile writes no budget: its cells train train.steps's default (PC²'s 100,000 steps, scored every
    5,000), the one home of that value, exactly as when the profile wrote the numbers out."""
    assert SHARED["paper"].budget.steps is None and SHARED["paper"].budget.eval_every is None
    cfg = expand(load_spec(SWEEPS / "point_size.yaml"), "paper").cells[0].config
    assert (cfg.train.steps, cfg.train.eval_every) == (100_000, 5000)
    spec = _spec(grid={"priors.point_size": [0.04]}, profiles={"p": {"budget": {"eval_every": 9}}})
    plan = expand(spec, "p", shared=SHARED)
    assert (plan.profile.steps, plan.profile.eval_every) == (100_000, 9)
    assert plan.cells[0].config.train.steps == 100_000


def test_exclude_and_explicit_cells_and_paper_rows():
    spec = _spec(
        grid={"priors.num_views": [4, 10], "priors.point_size": [0.0075, 0.04]},
        exclude=[{"priors.num_views": 4, "priors.point_size": 0.0075}],
        cells=[{"label": "A", "set": {"priors.lambda_3d": 0.1}}, {"label": "B"}],
        paper={"table": "T5", "rows": [{"label": "10+0.04", "when": {"priors.num_views": 10, "priors.point_size": 0.04},
                                         "values": {"eval/f1": 0.461}}]},
    )
    plan = expand(spec, "smoke", shared=SHARED)
    names = [c.name for c in plan.cells]
    assert names == [f"{x} · H={h} · point_size={s}" for x in "AB" for h, s in ((4, 0.04), (10, 0.0075), (10, 0.04))]
    assert [c.config.priors.lambda_3d for c in plan.cells] == [0.1] * 3 + [1.0] * 3
    assert [c.paper.get("eval/f1") for c in plan.cells] == [None, None, 0.461] * 2
    assert plan.cells[2].paper_label == "10+0.04"


def test_optuna_trial_from_sampled_values():
    spec = _spec(search={"kind": "optuna", "num_samples": 3,
                         "space": {"priors.lambda_3d": {"type": "log_float", "low": 1e-3, "high": 10}}})
    plan = expand(spec, "smoke", shared=SHARED)
    assert plan.cells == () and plan.num_trials == 3
    cell = plan.sampled_cell({"priors.lambda_3d": 0.0123456})
    assert cell.label == "λ=0.01235 · seed 0"
    assert cell.config.priors.lambda_3d == 0.0123456 and cell.config.train.steps == 20
    assert plan.names({"priors.lambda_3d": 0.0123456}) == (cell.name, cell.label)
    # Naming a trial (the driver's callbacks) resolves no config: a value the config rejects still has a name.
    assert plan.names({"priors.lambda_3d": -1.0}) == ("λ=-1", "λ=-1 · seed 0")
    with pytest.raises(ConfigError, match="priors.lambda_3d"):
        plan.sampled_cell({"priors.lambda_3d": -1.0})


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("name: t\ngird: {priors.point_size: [0.04]}\n", "gird: unknown key; allowed: name, description"),
        ("name: t\ngrid: {priors.point_size: [0.04]}\nseeds: zero\n", "seeds: Input should be a valid list"),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nresources: {cpus_per_worker: many}\n",
            "resources.cpus_per_worker",
        ),
        ("name: t\ngrid: {}\n", "grid: empty"),
        ("name: t\ngrid: {priors.point_size: []}\n", "grid.priors.point_size: empty list"),
        ("name: t\ngrid: {priors.pointsize: [0.04]}\n", "grid.priors.pointsize: unknown config field"),
        ("name: t\ngrid: {priors.point_size: [2.0]}\n", "priors.point_size: Input should be less than or equal to 1"),
        ("name: t\ngrid: {priors.render_kind: [sparkly]}\n", "priors.render_kind"),
        (
            "name: t\nsearch: {kind: optuna, space: {priors.lambda_3d: {type: log_float, low: 10, high: 1}}}\n",
            "search.space.priors.lambda_3d: low (10.0) must be < high (1.0)",
        ),
        (
            "name: t\nsearch: {kind: optuna, space: {priors.point_size: {type: float, low: 0.01, high: 3}}}\n",
            "search.space.priors.point_size=3.0",
        ),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nmetric: {name: eval/iou}\n",
            "metric.name: 'eval/iou' is not reported",
        ),
        ("name: t\ngrid: {priors.point_size: [0.04]}\nmetric: {name: eval/f1/teddybear}\n", "metric.name"),
        ("name: t\ngrid: {train.steps: [10]}\n", "grid.train.steps: set it through the profile's budget.steps"),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nexclude: [{priors.point_size: 0.05}]\n",
            "exclude[0].priors.point_size",
        ),
        ("name: t\n- not a mapping\n", "not valid YAML"),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nseeds: {min: 3, max: 2, until: settled}\n",
            "seeds: min (3) must be ≤ max (2)",
        ),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nseeds: {min: 0, max: 2, until: settled}\n",
            "seeds: min: Input should be greater than or equal to 1",
        ),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nseeds: {min: 1, max: 2, until: done}\n",
            "seeds: until: Input should be 'settled'",
        ),
        ("name: t\ngrid: {priors.point_size: [0.04]}\nseeds: {min: 1, max: 2}\n", "seeds: until: Field required"),
        ("name: t\ngrid: {priors.point_size: [0.04]}\nseeds: []\n", "seeds: empty list"),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nsettle: {margin: -0.1}\n",
            "settle.margin: Input should be greater than 0",
        ),
        (
            "name: t\ngrid: {priors.point_size: [0.04]}\nseeds: {min: 2, max: 3, until: settled}\n"
            "scheduler: {kind: asha}\n",
            "scheduler: seeds until settled compares finished trials",
        ),
    ],
)
def test_bad_spec_exits_2_naming_the_field_and_writes_nothing(body, needle, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "bad.yaml"
    spec.write_text(body)
    assert run.main([str(spec), "--smoke"]) == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert err.startswith("error: ") and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--set", "priors.pointsize=0.1"], "--set priors.pointsize: unknown config field"),
        (["--set", "priors.point_size=0.1"], "--set priors.point_size: this spec sweeps it"),
        (["--set", "train.lr"], "must look like key=value"),
        (["--profile", "huge"], "profile 'huge': unknown; available: local, paper, smoke"),
        (["--profile", "local", "--smoke"], "--smoke means --profile smoke"),
        (["--resume"], "holds no sweep to resume"),
        (["--budget", "2h"], "--budget: only seeds run until settled spend a budget; add --until-settled"),
        (
            ["--until-settled", "--budget", "2 hours"],
            "--budget '2 hours': give a wall time (2h, 45m, 30s; at most 366 days) or a number of trials (1 to 100000)",
        ),
        (["--until-settled", "--budget", "²"], "--budget '²': give a wall time"),
        (["--until-settled", "--budget", "9" * 5001], "--budget '" + "9" * 40 + "'…: give a wall time"),
        (["--until-settled", "--budget", "1" + "0" * 400], "number of trials (1 to 100000)"),
        (["--until-settled", "--budget", "1" + "0" * 400 + "s"], "at most 366 days"),
        (["--until-settled", "--budget="], "--budget '': give a wall time"),
        (["--budget="], "--budget '': give a wall time"),
        (["--until-settled", "--budget", "0"], "--budget '0': give a wall time"),
        (
            ["--until-settled", "--budget", "9"],
            "--budget 9: round 1 alone runs 10 trials (every cell at 2 seeds); give at least 10",
        ),
    ],
)
def test_bad_command_line_exits_2(argv, needle, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert run.main([str(SWEEPS / "point_size.yaml"), *argv]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and err.startswith("error: ")
    assert list(tmp_path.iterdir()) == []


def test_until_settled_refuses_an_optuna_spec_and_a_resume_keeps_the_seeds_it_started_with(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    assert run.main([str(SWEEPS / "lambda.yaml"), "--smoke", "--until-settled"]) == 2
    assert "--until-settled: search.kind optuna samples one trial per point" in capsys.readouterr().err
    state = tmp_path / "results" / "point_size" / "smoke" / "sweep.json"
    state.parent.mkdir(parents=True)
    state.write_text("{}")
    assert run.main([str(SWEEPS / "point_size.yaml"), "--smoke", "--resume", "--budget", "2h"]) == 2
    assert "drop --until-settled and --budget" in capsys.readouterr().err


def test_seeds_until_settled_from_the_spec_or_the_flag():
    rule = {"min": 3, "max": 6, "until": "settled"}
    spec = Spec.model_validate({"name": "t", "grid": {"priors.point_size": [0.02, 0.04]}, "seeds": rule})
    assert spec.sequential.looks == 4 and spec.seed_values == [0, 1, 2, 3, 4, 5]
    assert spec.until_settled() is spec
    listed = Spec.model_validate({"name": "t", "grid": {"priors.point_size": [0.02, 0.04]}, "seeds": [4]})
    assert listed.sequential is None and listed.until_settled().seeds.model_dump() == {
        "min": 2,
        "max": 5,
        "until": "settled",
    }
    long = Spec.model_validate({"name": "t", "grid": {"priors.point_size": [0.02]}, "seeds": list(range(7))})
    assert long.until_settled().seeds.max == 7
    plan = expand(spec, "smoke")
    assert plan.num_trials == 12 and plan.rounds == 4
    assert [(c.label, plan.round_of(c)) for c in plan.cells[:6]] == [
        ("point_size=0.02 · seed 0", 1), ("point_size=0.02 · seed 1", 1), ("point_size=0.02 · seed 2", 1),
        ("point_size=0.02 · seed 3", 2), ("point_size=0.02 · seed 4", 3), ("point_size=0.02 · seed 5", 4)]
    assert [c.label for c in plan.first_round] == [
        f"point_size={v} · seed {s}" for v in ("0.02", "0.04") for s in range(3)
    ]
    # The state a resume reads back validates to the same spec.
    assert Spec.model_validate(spec.model_dump(mode="json")) == spec
    assert [parse_budget(t) for t in ("2h", "45m", "30s", "1.5h", "12")] == [
        SeedBudget(seconds=7200.0),
        SeedBudget(seconds=2700.0),
        SeedBudget(seconds=30.0),
        SeedBudget(seconds=5400.0),
        SeedBudget(trials=12),
    ]


def test_a_dry_run_until_settled_says_the_rule_the_worst_case_and_its_time(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert (
        run.main(
            [
                str(SWEEPS / "point_size.yaml"),
                "--smoke",
                "--dry-run",
                "--no-estimate",
                "--until-settled",
                "--budget",
                "45m",
            ]
        )
        == 0
    )
    out = " ".join(capsys.readouterr().out.split())  # lines wrapped at the terminal's width, joined
    assert ("search: grid, seeds until settled: round 1 = 5 cells × 2 seeds = 10 trials; worst case 25 trials "
            "(5 cells × 5 seeds, 4 looks)") in out
    assert ("rule: each cell against point_size=0.0075 on eval/f1; settled when the interval excludes 0 (better/worse) "
            "(no settle.margin: no level verdict); else one more seed, up to 5") in out
    assert "Bonferroni" in out and "budget: 45 min wall time" in out
    assert "point_size=0.04 · seed 4 (priors.point_size=0.04) [round 4, if still open]" in out
    assert list(tmp_path.iterdir()) == []
    # The estimate (calibrated in the slow tier's dry runs) times the worst case and says so.
    assert Estimate(25, 60.0, 2, 780.0, worst_case=True).text().startswith(
        "estimate: worst case, 25 trials × ~1.0 min, 2 at a time → ~13.0 min wall on this machine")


def test_a_finished_sweep_folder_is_not_overwritten(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "results" / "point_size" / "smoke").mkdir(parents=True)
    assert run.main([str(SWEEPS / "point_size.yaml"), "--smoke"]) == 2
    assert "pass --resume" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("resources", "cpus", "gpus", "trials", "want"),
    [
        ({}, 2, 0, 5, (1.0, 2)),  # local mode: the trial's actor trains on its one CPU
        ({}, 2, 0, 1, (1.0, 1)),  # never more than the trials
        ({"max_concurrent_trials": 1}, 16, 0, 5, (1.0, 1)),
        ({"workers_per_trial": 1}, 2, 0, 5, (1.01, 1)),  # worker + the trial's token CPU: 2 would deadlock
        ({"workers_per_trial": 1, "cpus_per_worker": 0.5}, 2, 0, 5, (0.51, 3)),
        ({"workers_per_trial": 2, "cpus_per_worker": 4, "gpus_per_worker": 1}, 64, 4, 9, (8.01, 2)),
    ],
)
def test_concurrency_fits_the_cluster(resources, cpus, gpus, trials, want):
    conc = plan_concurrency(Resources(**resources), cpus, gpus, trials)
    assert (round(conc.cpus_per_trial, 6), conc.max_concurrent) == want
    assert conc.max_concurrent * conc.cpus_per_trial <= cpus


def test_a_trial_larger_than_the_cluster_is_refused():
    with pytest.raises(SpecError, match="one trial needs 4 CPUs and 1 GPUs but the cluster has 2 and 0"):
        plan_concurrency(Resources(cpus_per_worker=4, gpus_per_worker=1), 2, 0, 3)


PAPER_RESOURCES = {"workers_per_trial": 1, "cpus_per_worker": 4, "gpus_per_worker": 1}


@pytest.mark.parametrize(
    ("resources", "cpus", "gpus", "trials", "want"),
    [
        # An autoscaling GPU cluster that could grow to 8 GPUs: all 12 trials wait; nodes come as they do.
        (PAPER_RESOURCES, 72, 8, 12, 12),
        ({**PAPER_RESOURCES, "max_concurrent_trials": 3}, 72, 8, 12, 3),
        ({}, 2, 0, 5, 5),  # a fixed remote cluster: Tune queues what does not fit, nothing deadlocks in local mode
    ],
)
def test_a_remote_cluster_takes_its_cap_from_the_spec_not_from_the_nodes_up(resources, cpus, gpus, trials, want):
    assert plan_concurrency(Resources(**resources), cpus, gpus, trials, remote=True).max_concurrent == want


def test_a_remote_cluster_that_could_never_fit_a_trial_is_refused():
    # The same trial is refused locally for the GPUs present and remotely for the GPUs it could ever have.
    with pytest.raises(SpecError, match="one trial needs 4.01 CPUs and 1 GPUs but the cluster has 16 and 0"):
        plan_concurrency(Resources(**PAPER_RESOURCES), 16, 0, 3)
    with pytest.raises(SpecError, match="could offer at most 16 and 0; .* min_workers: 1"):
        plan_concurrency(Resources(**PAPER_RESOURCES), 16, 0, 3, remote=True)


# The local profile's overrides as sweeps/profiles.yaml wrote them out before it named configs/quick.yaml as
# its recipe (ef8ae6d): the main job's cells must resolve to the same configs.
LOCAL_BEFORE_THE_RECIPE = {
    "data.image_size": 64, "data.num_points": 512, "data.train_objects": 256, "data.val_objects": 16,
    "model.feature_dim": 32, "model.widths": [32, 64, 128], "model.voxel_resolutions": [16, 8, 8],
    "model.voxel_backend": "sparse", "diffusion.prediction": "x0", "diffusion.sample_steps": 10,
    "diffusion.timestep_spacing": "trailing", "priors.render_kind": "planar", "priors.lambda_3d": 0.1,
    "priors.render_size": 64, "train.batch_size": 4, "train.lr": 1.0e-3, "train.betas": [0.9, 0.99],
    "train.warmup_steps": 150, "train.log_every": 100, "eval.num_objects": 16, "eval.num_points": 512,
    "eval.save_clouds": 8,
}


def test_the_local_profile_starts_from_the_quick_config_and_resolves_the_main_job_as_before():
    recipe = SHARED["local"].overrides
    assert {k: recipe[k] for k in ("data.image_size", "priors.lambda_3d", "model.widths")} == {
        "data.image_size": 64, "priors.lambda_3d": 0.1, "model.widths": [32, 64, 128]}
    assert not {"train.steps", "train.eval_every", "train.threads", "train.out_dir"} & set(recipe)
    for cell in expand(load_spec(SWEEPS / "point_size.yaml"), "local").cells:
        flat, default = cell.config.flat(), Config().flat()
        assert {k: flat[k] for k in LOCAL_BEFORE_THE_RECIPE} == LOCAL_BEFORE_THE_RECIPE
        assert (flat["train.steps"], flat["train.eval_every"], flat["train.threads"]) == (2000, 2000, 1)
        assert flat["train.out_dir"] == default["train.out_dir"]
        # Nothing else differs from the defaults: the recipe brought no field the profile did not set before.
        changed = {k for k in flat if flat[k] != default[k]} - {"priors.point_size"}
        before = {k for k, v in LOCAL_BEFORE_THE_RECIPE.items() if v != default[k]}
        assert changed == before | {"train.steps", "train.eval_every", "train.threads"}


def test_a_recipe_is_one_home_read_by_the_profile_and_checked_like_a_config(tmp_path):
    recipe = tmp_path / "configs" / "cpu.yaml"
    recipe.parent.mkdir()
    recipe.write_text("priors:\n  lambda_3d: 0.3\ntrain:\n  steps: 9\n  out_dir: runs/x\n")
    profiles = tmp_path / "sweeps" / "profiles.yaml"
    profiles.parent.mkdir()
    profiles.write_text("p:\n  recipe: ../configs/cpu.yaml\n  overrides: {train.lr: 0.01}\n")
    assert load_profiles(profiles)["p"].overrides == {"priors.lambda_3d": 0.3, "train.lr": 0.01}
    recipe.write_text("priors:\n  lambda_3d: 0.7\n")  # changed in its one home, changed for the profile
    assert load_profiles(profiles)["p"].overrides["priors.lambda_3d"] == 0.7
    recipe.write_text("priors:\n  lambda_3d: -1\n")
    with pytest.raises(SpecError, match=r"recipe .*cpu.yaml: priors.lambda_3d: Input should be greater than or equal"):
        load_profiles(profiles)
    with pytest.raises(ValueError, match=r"profiles\.local\.recipe\s+Extra inputs are not permitted"):
        _spec(grid={"priors.point_size": [0.04]}, profiles={"local": {"recipe": "../configs/quick.yaml"}})


def test_lambda_source_names_the_profile_that_sets_it():
    spec = load_spec(SWEEPS / "point_size.yaml")
    local, smoke = expand(spec, "local"), expand(spec, "smoke")
    assert {c.config.priors.lambda_3d for c in local.cells} == {0.1}
    assert lambda_source(spec, "local", local.fixed, local.sets) == "profile local"
    assert lambda_source(spec, "smoke", smoke.fixed, smoke.sets) == "the config default"
    assert lambda_source(spec, "smoke", smoke.fixed, {"priors.lambda_3d": 0.5}) == "--set"
    assert lambda_source(load_spec(SWEEPS / "lambda.yaml"), "local", {}, {}) == "the spec's search"


def test_the_paper_profile_names_every_missing_input_and_the_command_that_makes_it(tmp_path, monkeypatch, capsys):
    from tests.datasets_fixtures import make_co3d

    root = make_co3d(tmp_path / "co3d", categories=("teddybear",)).root
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CDM_INPUTS", str(tmp_path / "inputs"))
    args = [str(SWEEPS / "prior_type.yaml"), "--dry-run", "--no-estimate", "--profile", "paper",
            "--set", f"data.root={root}", "--set", "data.kind=co3d"]
    assert run.main(args) == 2
    captured = capsys.readouterr()
    # It still plans (issue 44): the card, the plan and the GPU-hours, which read no input, then the error.
    assert "protocol card:" in captured.out and "GPU-hours" in captured.out and "(MISSING)" in captured.out
    assert "estimate: no calibration steps (they read the missing inputs)" in captured.out
    error = captured.err.strip().splitlines()[-1]
    assert len(captured.err.strip().splitlines()) == 1
    weights, maps = error.removeprefix("error: ").split("; priors.")
    assert weights.startswith(f"model.encoder_weights: {tmp_path}/inputs/msn/vits16_800ep.pth.tar does not exist")
    assert (
        "make it with: curl -L --create-dirs -o $CDM_INPUTS/msn/vits16_800ep.pth.tar https://dl.fbaipublicfiles.com"
        in weights
    )
    assert maps.startswith(f"depth_maps: {tmp_path}/inputs/depth_maps does not exist")
    assert (
        f"make it with: python -m cdm.tools.export_views --out views/ --set data.kind=co3d --set data.root={root}"
        in maps
    )
    # A user without the weights trains PC²'s trainable CNN instead: then only the depth maps are missing.
    assert run.main([*args, "--set", "model.encoder=cnn"]) == 2
    assert (
        capsys.readouterr()
        .err.strip()
        .splitlines()[-1]
        .startswith(f"error: priors.depth_maps: {tmp_path}/inputs/depth_maps")
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["co3d"]


def test_table_4_trains_one_model_per_co3d_class_with_that_class_s_paper_row(tmp_path):
    from tests.datasets_fixtures import make_co3d

    root = make_co3d(tmp_path / "co3d", categories=("hydrant", "teddybear", "toytruck"), frames=3).root
    plan = expand(load_spec(SWEEPS / "priors_2d_3d.yaml"), "paper", {"data.root": str(root), "data.kind": "co3d"})
    assert len(plan.cells) == 12 and {c.config.data.categories for c in plan.cells} == {
        ("hydrant",),
        ("teddybear",),
        ("toytruck",),
    }
    both = next(c for c in plan.cells if c.config.priors.prior_3d and c.config.data.categories == ("toytruck",)
                and c.config.priors.prior_2d == "depth")
    assert both.paper_label == "+2D+3D, toytruck" and both.paper == {"eval/cd": 125.40, "eval/f1": 0.474}
    stand_in = expand(load_spec(SWEEPS / "priors_2d_3d.yaml"), "local")
    assert len(stand_in.cells) == 4 and stand_in.cells[0].paper_label == "baseline (PC²)"


def test_the_small_profiles_leave_x0_unclamped_on_data_sets_whose_frames_pass_unit_extent(tmp_path):
    from tests.datasets_fixtures import make_co3d

    root = make_co3d(tmp_path / "co3d", categories=("teddybear",), frames=3).root
    spec = load_spec(SWEEPS / "point_size.yaml")
    assert expand(spec, "local").cells[0].config.diffusion.clip_x0 == 1.0  # the procedural frame fits [-1, 1]³
    for profile in ("smoke", "local"):
        on_co3d = expand(spec, profile, {"data.kind": "co3d", "data.root": str(root), "data.categories": ["teddybear"]})
        assert on_co3d.cells[0].config.diffusion.clip_x0 is None  # Co3D's world units


def test_relative_storage_is_refused_on_a_cluster(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = [str(SWEEPS / "point_size.yaml"), "--smoke", "--out", "results"]
    assert run.main([*argv, "--address", "127.0.0.1:6379"]) == 2
    err = capsys.readouterr().err
    assert "--out results: on a cluster give an absolute path" in err and "s3://" in err
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:6379")  # what `ray job submit` sets for its driver
    assert run.main(argv) == 2
    assert list(tmp_path.iterdir()) == []


def test_dry_run_names_missing_inputs(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CDM_INPUTS", str(tmp_path / "nothing"))
    code = run.main([str(SWEEPS / "global_features.yaml"), "--smoke", "--dry-run", "--out", str(tmp_path / "r")])
    captured = capsys.readouterr()
    assert code == 2 and captured.out.count("(MISSING)") == 5
    assert captured.err.strip().splitlines()[-1].startswith("error: model.global_embeddings: ")
    assert not (tmp_path / "r").exists()


def test_trial_labels_are_built_and_split_in_one_place():
    from sweeps.plan.trials import split_label, trial_label

    assert trial_label("point_size=0.04 · H=10", 3) == "point_size=0.04 · H=10 · seed 3"
    assert split_label(trial_label("point_size=0.04 · H=10", 3)) == ("point_size=0.04 · H=10", "3")
    assert split_label("point_size=0.04") == ("point_size=0.04", None)


def test_a_dry_run_lists_no_searched_key_as_fixed_and_says_where_asha_stops(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert run.main([str(SWEEPS / "lambda.yaml"), "--dry-run", "--no-estimate"]) == 0
    out = capsys.readouterr().out
    fixed = " ".join(out.split("\nfixed: ", 1)[1].split("\nprotocol card:", 1)[0].split())
    # The recipe's λ 0.1 is what the search replaces in every trial: not a fixed setting.
    assert "priors.lambda_3d" not in fixed and "priors.point_size=0.04" in fixed
    assert "priors.lambda_3d: log_float [0.001, 10]" in out
    # The local profile's evaluation halfway gives ASHA a rung before the last step (the spec promises it).
    assert "\nscheduler: asha, may stop a trial at step 700 of 1400\n" in out
    assert "ASHA stopping weak trials after their first evaluation" in " ".join(out.split())
    assert max(len(line.encode()) for line in out.splitlines()) <= 120


def test_a_scheduler_that_can_stop_nothing_is_said_in_one_line_and_not_run(tmp_path, monkeypatch, capsys):
    from sweeps.execute.tuner import _scheduler

    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "late.yaml"
    spec.write_text(f"{(SWEEPS / 'lambda.yaml').read_text()}\n".replace("grace_evals: 1", "grace_evals: 2"))
    assert run.main([str(spec), "--dry-run", "--no-estimate", "--smoke"]) == 0  # 20 steps, evaluations at 10, 20
    lines = capsys.readouterr().out.splitlines()
    line = next(i for i, text in enumerate(lines) if text.startswith("scheduler:"))
    assert lines[line] == ("scheduler: asha stops no trial under profile smoke: its first rung (step 20) is not before "
                           "the last step (20)")
    assert not lines[line + 1].startswith("  ")  # one line
    assert _scheduler(expand(load_spec(spec), "smoke")) is None  # and Tune runs without it
    assert _scheduler(expand(load_spec(SWEEPS / "lambda.yaml"), "smoke")) is not None


@pytest.mark.parametrize(("steps", "eval_every", "grace", "rf", "stops"), [
    (2000, 2000, 1, 2, []),  # the shared local profile: the only rung is the last step
    (1400, 700, 1, 2, [700]),
    (100, 10, 1, 3, [10, 30, 90]),
    (100, 10, 1, 2.5, [10, 30, 70]),  # rungs 25 and 62.5 are judged at the next evaluation
    (20, 10, 3, 2, []),  # a grace period past the budget
])
def test_asha_stops_where_rays_rungs_meet_an_evaluation(steps, eval_every, grace, rf, stops):
    from ray.tune.schedulers.async_hyperband import _Bracket

    from sweeps.plan.spec import Scheduler

    sch = Scheduler(kind="asha", grace_evals=grace, reduction_factor=rf)
    assert sch.stops(steps, eval_every) == stops
    assert Scheduler().stops(steps, eval_every) == []
    if grace * eval_every <= steps:  # Ray's own rungs (it refuses a grace period past max_t), each judged at the
        rungs = [m for m, _ in _Bracket(grace * eval_every, steps, rf, 0)._rungs]  # next evaluation
        judged = {min(steps, -(-int(-(-m // 1)) // eval_every) * eval_every) for m in rungs}
        assert sorted(s for s in judged if s < steps) == stops


def test_a_budget_in_compute_sets_the_trials_config_and_counts_asha_in_seconds(tmp_path):
    plan = expand(load_spec(SWEEPS / "local_recipe.yaml"), "local")
    assert plan.profile.time_axis == ("train/compute_s", 190.0, 95.0)
    assert {k: plan.fixed[k] for k in ("train.compute_budget_s", "train.eval_every_s", "train.steps")} == {
        "train.compute_budget_s": 190.0, "train.eval_every_s": 95.0, "train.steps": 4000}
    assert plan.spec.scheduler.stops(190.0, 95.0) == [95.0]
    # Done: its compute spent (at any step), or its steps; stopped early: neither.
    assert plan.profile.completed(1234, {"train/compute_s": 190.2}) and plan.profile.completed(4000, {})
    assert not plan.profile.completed(2100, {"train/compute_s": 96.0})
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: b\ngrid: {train.lr: [0.001]}\nprofiles: {smoke: {budget: {eval_every_s: 5}}}\n")
    with pytest.raises(SpecError, match="budget.eval_every_s: only with budget.compute_s"):
        load_spec(bad)
    bad.write_text("name: b\ngrid: {train.lr: [0.001]}\nbase: {train.compute_budget_s: 5}\n")
    with pytest.raises(SpecError, match="train.compute_budget_s.*budget.compute_s"):
        load_spec(bad)
