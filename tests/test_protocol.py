"""The protocol card: a diff of the whole resolved config against the table's reference record, and where it is
shown."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from cdm.config import Config, config_field_paths, load_config
from cdm.data.shapenet import SYNSETS
from sweeps import run
from sweeps.execute.driver import table_settings
from sweeps.plan import references
from sweeps.plan.profiles import load_profiles
from sweeps.plan.protocol import NO_DEVIATIONS, CardContext, ProtocolCard, plan_card, protocol_card
from sweeps.plan.references import DATA_SETS, TABLES, Stated, record, show
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from tests.datasets_fixtures import make_co3d, make_shapenet

ROOT = Path(__file__).resolve().parent.parent
SWEEPS = ROOT / "sweeps"
SPECS = sorted(p for p in SWEEPS.glob("*.yaml") if p.name != "profiles.yaml")


@pytest.fixture(scope="module")
def shapenet(tmp_path_factory):
    """All 13 R2N2 classes, BDM's split file, two views each: enough for a dry run (the first train model of
    each class moves to BDM's test split, the second stays in train), not for training."""
    names = {name: synset for synset, name in SYNSETS.items()}
    return make_shapenet(tmp_path_factory.mktemp("sn13"), per_split={"train": 2, "val": 0, "test": 1}, views=2,
                         bdm_split=True, synsets=names)


@pytest.fixture(scope="module")
def co3d(tmp_path_factory):
    return make_co3d(tmp_path_factory.mktemp("co3d3"), categories=("hydrant", "teddybear", "toytruck"), frames=3,
                     splits={"train": 1, "val": 1, "test": 0})


def _card(spec: str, profile: str = "paper", **sets) -> ProtocolCard:
    return plan_card(expand(load_spec(SWEEPS / f"{spec}.yaml"), profile, sets))


def _fields(card: ProtocolCard) -> list[str]:
    """The fields a card lists (config fields, and stated ones the config lacks), in its order."""
    return [line.split(":")[0] for line in card.deviations if "." in line.split(":")[0]]


@pytest.mark.parametrize("table", [None, *TABLES])
@pytest.mark.parametrize("kind", DATA_SETS)
def test_every_record_has_an_entry_for_every_config_field(table, kind):
    assert sorted(set(config_field_paths()) - set(record(table, kind))) == []


def test_every_table_of_the_shipped_specs_has_a_record():
    tables = {load_spec(p).paper.table for p in SPECS if load_spec(p).paper}
    assert tables == set(TABLES)
    with pytest.raises(KeyError, match="'Table 9': no reference record"):
        record("Table 9", "co3d")


def _written_twice(source: str) -> list[str]:
    """Fields whose ``Stated`` value in a record's ``source`` is written out although it equals the config default
    or the paper profile's value (on either data set)."""
    defaults = Config().flat()
    paper = load_profiles()["paper"]
    ran = [{**paper.overrides, **paper.datasets.get(kind, {})} for kind in DATA_SETS]

    def norm(value):
        return list(value) if isinstance(value, (list, tuple)) else value

    twice = []
    for node in ast.walk(ast.parse(source)):
        for key, entry in zip(node.keys, node.values, strict=True) if isinstance(node, ast.Dict) else ():
            if not (isinstance(key, ast.Constant) and isinstance(entry, ast.Call) and entry.args):
                continue
            if getattr(entry.func, "id", None) != "Stated" or any(k.arg == "accepts" for k in entry.keywords):
                continue
            try:
                value = ast.literal_eval(entry.args[0])
            except ValueError:  # a name: _DEFAULT or _PAPER, read from their home
                continue
            homes = [defaults, *ran]
            if any(key.value in home and norm(value) == norm(home[key.value]) for home in homes):
                twice.append(key.value)
    return twice


def test_no_paper_value_is_written_both_in_the_config_and_in_the_records():
    source = Path(references.__file__).read_text()
    assert _written_twice(source) == []
    # The check finds a value planted twice: λ's 1.0 written out instead of read from cdm/config.py.
    read = '"priors.lambda_3d": Stated(\n        _DEFAULT,'
    planted = source.replace(read, '"priors.lambda_3d": Stated(\n        1.0,')
    assert planted != source and _written_twice(planted) == ["priors.lambda_3d"]
    planted = source.replace('"model.denoiser": Stated(_PAPER,', '"model.denoiser": Stated("pvcnn2",')
    assert planted != source and _written_twice(planted) == ["model.denoiser"]
    # The records hold the config's own values, so the card compares with what the config says.
    defaults = Config().flat()
    for kind in DATA_SETS:
        for path in ("priors.lambda_3d", "train.betas", "train.warmup_steps", "train.steps", "eval.f1_threshold"):
            assert record(None, kind)[path].value == defaults[path]
    assert (defaults["priors.lambda_3d"], defaults["train.betas"]) == (1.0, [0.95, 0.999])
    assert (defaults["train.warmup_steps"], defaults["train.steps"]) == (2000, 100_000)
    # Where the paper differs from the default, the paper profile is the home, read per data set.
    assert record(None, "co3d")["data.num_points"].value == 16384
    assert record(None, "shapenet_r2n2")["data.num_points"].value == defaults["data.num_points"] == 4096
    assert record(None, "co3d")["model.denoiser"].value == "pvcnn2"


def test_the_paper_profile_writes_no_value_the_config_default_already_holds():
    paper, defaults = load_profiles()["paper"], Config().flat()

    def norm(value):
        return list(value) if isinstance(value, (list, tuple)) else value

    fields = {**paper.overrides, **{k: v for d in paper.datasets.values() for k, v in d.items()}}
    assert {k: v for k, v in fields.items() if norm(v) == norm(defaults[k])} == {}
    assert (paper.budget.steps, paper.budget.eval_every) == (None, None)


@pytest.mark.parametrize(
    "name, pattern",
    [
        ("λ's 1.0", r"lambda_3d\b.*[(:] *1\.0\b|Stated\(1\.0.*[Ee]q\. 6"),
        ("PC²'s betas", r"0\.95, *0\.999"),
        ("warm-up 2,000", r"warmup_steps\b.*\b2_?000\b"),
        ("steps 100,000", r"steps\b.*\b100_?000\b"),
    ],
)
def test_each_paper_value_the_issue_names_is_written_in_one_place(name, pattern):
    """The bar of issue 45: each of these is written in one file of cdm/ and sweeps/, as its default in
    cdm/config.py (whose docstrings may repeat it), and read from there by the records and the paper profile."""
    hits = [
        f"{path.relative_to(ROOT)}:{n}"
        for folder in ("cdm", "sweeps")
        for path in sorted((ROOT / folder).rglob("*"))
        if path.suffix in (".py", ".yaml")
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if re.search(pattern, line)
    ]
    assert {h.split(":")[0] for h in hits} == {"cdm/config.py"}, (name, hits)


@pytest.mark.parametrize("kind", DATA_SETS)
def test_a_config_made_of_the_records_values_has_no_deviations(kind, tmp_path):
    """Every stated value is a valid value of its field, and a config holding them all has a clean card."""
    (tmp_path / "pc_dict_v2.json").write_text("{}")
    fields = set(config_field_paths())
    rec = record(None, kind)
    values = {p: e.value for p, e in rec.items() if isinstance(e, Stated) and e.accepts is None and p in fields}
    cfg = load_config(None, {**values, "data.root": str(tmp_path), "data.categories": ["chair"],
                             "model.encoder_weights": "vits16_800ep.pth.tar", "priors.depth_maps": "maps"})
    card = protocol_card(cfg, CardContext((kind,)))
    lacking = [p for p, e in rec.items() if isinstance(e, Stated) and p not in fields and e.applies(cfg.flat())]
    assert card.deviations == tuple(f"{p}: not a field of this config, so not {rec[p].shown} ({rec[p].source})"
                                    for p in lacking)  # what this code cannot be set to yet (model.denoiser)
    assert (card.lines()[0] == NO_DEVIATIONS) == (not lacking)
    assert not any(n.startswith("not compared") for n in card.notes)


PLANTS = [  # (spec, data set, group, field, value): one or more per config group, on the paper profile
    ("shapenet", "shapenet_r2n2", "data", "data.num_points", 2048),
    ("co3d", "co3d", "data", "data.image_size", 128),
    ("shapenet", "shapenet_r2n2", "model", "model.raster_radius", 0.02),
    ("co3d", "co3d", "model", "model.time_embed_dim", 32),
    ("shapenet", "shapenet_r2n2", "diffusion", "diffusion.beta_end", 0.02),
    ("co3d", "co3d", "diffusion", "diffusion.num_steps", 500),
    ("shapenet", "shapenet_r2n2", "priors", "priors.target", "x_t_literal"),
    ("co3d", "co3d", "priors", "priors.point_size", 0.02),
    ("shapenet", "shapenet_r2n2", "train", "train.ema_decay", 0.999),
    ("co3d", "co3d", "train", "train.grad_clip", 5.0),
    ("co3d", "co3d", "train", "train.precision", "bf16"),
    ("shapenet", "shapenet_r2n2", "eval", "eval.f1_threshold", 0.02),
    ("co3d", "co3d", "eval", "eval.protocol", "quick"),
    ("bdm_blend", "shapenet_r2n2", "sampling.blend", "sampling.blend.select_prob", 0.3),
    ("bdm_blend", "shapenet_r2n2", "sampling.blend", "sampling.blend.window_steps", 8),
]


def test_the_plants_cover_every_config_group():
    groups = {p.rsplit(".", 1)[0] for p in config_field_paths()}
    assert {plant[2] for plant in PLANTS} == groups


@pytest.mark.parametrize(("spec", "kind", "group", "field", "value"), PLANTS, ids=[p[3] for p in PLANTS])
def test_a_deviation_planted_in_any_config_group_is_listed(spec, kind, group, field, value, shapenet, co3d):
    root = str((shapenet if kind == "shapenet_r2n2" else co3d).root)
    before = _card(spec, **{"data.root": root})
    after = _card(spec, **{"data.root": root, field: value})
    assert field not in _fields(before) and field in _fields(after)
    line = next(d for d in after.deviations if d.startswith(f"{field}: "))
    entry = record(load_spec(SWEEPS / f"{spec}.yaml").paper.table, kind)[field]
    assert line == f"{field}: {show(value)}, not {entry.shown} ({entry.source})"
    assert not after.faithful and NO_DEVIATIONS not in after.lines()


def test_ema_and_raster_radius_set_together_are_both_listed_by_the_dry_run(shapenet, tmp_path, monkeypatch, capsys):
    (tmp_path / "msn").mkdir()
    (tmp_path / "msn" / "vits16_800ep.pth.tar").write_bytes(b"")  # the paper profile's encoder weights: present
    monkeypatch.setenv("CDM_INPUTS", str(tmp_path))
    args = [
        str(SWEEPS / "shapenet.yaml"),
        "--dry-run",
        "--no-estimate",
        "--profile",
        "paper",
        "--set",
        f"data.root={shapenet.root}",
        "--set",
        "train.ema_decay=0.999",
        "--set",
        "model.raster_radius=0.02",
    ]
    assert run.main(args) == 0
    card = capsys.readouterr().out.split("protocol card:\n", 1)[1]
    assert "  deviation: model.raster_radius: 0.02, not 0.0075 (PC² experiments/model/projection_model.py" in card
    assert "  deviation: train.ema_decay: 0.999, not null (PC² experiments/config/structured.py: use_ema False)" in card


def test_the_paper_profile_lists_the_encoder_and_the_denoiser_only_when_they_deviate(shapenet):
    root = str(shapenet.root)
    plan = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper", {"data.root": root})
    cfg = plan.cells[0].config
    fields = _fields(plan_card(plan))
    assert ("model.encoder" in fields) == (cfg.model.encoder != "vit_s16")
    # PC²'s PVCNN2 (issue 32): until the config can select it, the card says the denoiser is not PC²'s
    assert ("model.denoiser" in fields) == (cfg.flat().get("model.denoiser") != "pvcnn2")
    cnn = _card("shapenet", **{"data.root": root, "model.encoder": "cnn", "model.feature_dim": 32})
    assert "model.encoder: cnn, not vit_s16 (PC² experiments/config/structured.py: image_feature_model " \
           "vit_small_patch16_224_msn, frozen)" in cnn.deviations
    assert "model.feature_dim" in _fields(cnn)


def test_batch_size_lambda_and_point_counts_are_compared_with_what_the_sources_say(shapenet, co3d):
    bdm = "train.batch_size: 8, not 16 (BDM experiments/example_train.sh: dataloader.batch_size; the paper states none)"
    assert bdm in _card("shapenet", **{"data.root": str(shapenet.root), "train.batch_size": 8}).deviations
    assert "train.batch_size" not in _fields(
        _card("shapenet", **{"data.root": str(shapenet.root), "train.batch_size": 16})
    )
    assert "train.batch_size" not in _fields(_card("co3d", **{"data.root": str(co3d.root), "train.batch_size": 8}))
    assert "train.batch_size: 16, not 8 (PC² experiments/config/structured.py: DataloaderConfig.batch_size; " \
           "the paper states none)" in _card("co3d", **{"data.root": str(co3d.root), "train.batch_size": 16}).deviations
    # λ: Eq. 6 weighs the prior term by 1; the free choice is its per-pixel mean, said in a note
    unit = _card("co3d", **{"data.root": str(co3d.root), "priors.lambda_3d": 1.0})
    assert "priors.lambda_3d" not in _fields(unit) and not any("ours" in n for n in unit.notes if "λ" in n)
    assert any(n.startswith("3D prior: each view's term is the mean over its pixels") for n in unit.notes)
    tenth = _card("co3d", **{"data.root": str(co3d.root), "priors.lambda_3d": 0.1})
    assert "priors.lambda_3d: 0.1, not 1 (paper Eq. 6: the prior term has unit weight (Eq. 5's λ is the ELBO's))" \
        in tenth.deviations
    # Table 5's reference is PC² on Co3D, 16,384 points: its paper plan lists no point count, even on a stand-in
    table_5 = _card("frames_point_size")
    assert not {"data.num_points", "eval.num_points"} & set(_fields(table_5))
    assert "data.num_points: 4096, not 16384 (paper §4; PC² experiments/config/structured.py: max_points)" in \
        _card("frames_point_size", **{"data.num_points": 4096}).deviations


def test_swept_fields_are_the_tables_axes_and_free_choices_are_noted(shapenet):
    table_1 = _card("shapenet", **{"data.root": str(shapenet.root)})  # its PC² cell has no 2D prior, its CDM cell one
    assert not {"priors.prior_2d", "priors.prior_3d", "data.categories"} & set(_fields(table_1))
    prediction = _card("prediction")
    assert "diffusion.prediction" not in _fields(prediction)  # x0 and v are the ablation, not a deviation
    local = _card("point_size", "local")
    assert "note: free choices (no source states them): diffusion.timestep_spacing = trailing" in local.lines()
    assert local.lines()[0].startswith("deviation: data set: the procedural data set stands in for Co3D v2")
    fields = _fields(local)
    present = [f for f in fields if f in config_field_paths()]
    assert present == sorted(present, key=config_field_paths().index)  # config order, merged over the cells
    assert fields[len(present):] == [f for f in fields if f not in present]  # then what the config cannot hold
    for field in ("data.num_points", "diffusion.prediction", "diffusion.sampler", "train.steps", "eval.protocol"):
        assert field in fields, field


def test_a_field_the_record_lacks_is_named_not_passed_over(monkeypatch):
    monkeypatch.delitem(references._COMMON, "train.lr")
    card = protocol_card(load_config(None, {"train.lr": 5e-4}))
    assert "not compared (no entry in sweeps/plan/references.py): train.lr" in card.notes


def test_a_missing_split_file_is_the_data_protocols_line_and_one_model_per_class_is_compared(shapenet, co3d, tmp_path):
    bare = make_shapenet(tmp_path / "bare", per_split={"train": 1, "test": 1}, views=2)
    card = _card("prior_type", **{"data.root": str(bare.root), "data.kind": "shapenet_r2n2"})
    assert (
        card.deviations[0]
        == "split: PC15k's test folders, not BDM's R2N2 test split (put BDM's pc_dict_v2.json in data.root)"
    )
    assert not any(d.startswith("split:") for d in _card("shapenet", **{"data.root": str(shapenet.root)}).deviations)
    # the references train one model per class: Table 5's teddybear model trained with hydrant is listed
    two = _card("frames", **{"data.root": str(co3d.root), "data.categories": ["teddybear", "hydrant"]})
    assert "data.categories: [teddybear, hydrant], not one category per model (PC² experiments/config/structured.py: " \
           "CO3DConfig.category)" in two.deviations
    assert "data.categories" not in _fields(_card("frames", **{"data.root": str(co3d.root)}))
    assert ProtocolCard(()).lines() == [NO_DEVIATIONS]


def test_table_2_on_shapenet_uses_car_and_lamp_stands_in_only_on_procedural_data(shapenet):
    spec = load_spec(SWEEPS / "bdm_blend.yaml")
    ours = expand(spec, "paper", {"data.root": str(shapenet.root)})
    labels = {c.paper_label for c in ours.cells}
    assert {c.config.data.categories[0] for c in ours.cells} == {"airplane", "car", "chair", "sofa", "table"}
    assert "CDM+BDM, car" in labels and not any("lamp" in label for label in labels)
    procedural = expand(spec, "paper")
    assert "CDM, car (lamp stands in)" in {c.paper_label for c in procedural.cells}
    assert any("lamp stands in for car" in d for d in plan_card(procedural).deviations)
    # BDM blends with PVD's checkpoints; a prior trained here is listed
    assert any(
        d.startswith("sampling.blend.prior_checkpoint: auto, not PVD's checkpoint") for d in plan_card(ours).deviations
    )


def test_depth_renders_that_average_surfaces_are_a_deviation():
    cfg = expand(load_spec(SWEEPS / "point_size.yaml"), "paper").cells[0].config
    ctx = CardContext(("co3d",), table="Table 5", swept=frozenset({"priors.point_size"}))
    assert "priors.depth_layer" not in _fields(protocol_card(cfg, ctx))  # the front layer, as PyTorch3D
    averaged = protocol_card(cfg.replace(**{"priors.depth_layer": None}), ctx)
    assert "priors.depth_layer: null, not a front layer (PyTorch3D's z-buffer keeps the nearest point) (paper §4: " \
           "PyTorch3D renders the 3D prior images)" in averaged.deviations


def test_the_paper_profile_trains_in_pcs_fp16_and_the_card_names_any_other_precision(co3d, shapenet, tmp_path,
                                                                                     monkeypatch, capsys):
    """Acceptance (issue 41): Table 5's paper card has no precision line; --set train.precision=fp32 adds
    one naming PC²'s mixed_precision; on ShapeNet the source is BDM's, the same field."""
    assert all(
        cell.config.train.precision == "fp16" for cell in expand(load_spec(SWEEPS / "frames.yaml"), "paper").cells
    )
    assert "train.precision" not in _fields(_card("frames", **{"data.root": str(co3d.root)}))
    pc2 = ("train.precision: fp32, not fp16 (PC² experiments/config/structured.py: RunConfig.mixed_precision 'fp16', "
           "Accelerate's autocast and loss scale)")
    assert pc2 in _card("frames", **{"data.root": str(co3d.root), "train.precision": "fp32"}).deviations
    bdm = _card("shapenet", **{"data.root": str(shapenet.root), "train.precision": "fp32"}).deviations
    assert any(d.startswith("train.precision: fp32, not fp16 (BDM experiments/config/structured.py: "
                            "RunConfig.mixed_precision") for d in bdm)
    (tmp_path / "msn").mkdir()
    (tmp_path / "msn" / "vits16_800ep.pth.tar").write_bytes(b"")
    monkeypatch.setenv("CDM_INPUTS", str(tmp_path))
    args = [
        str(SWEEPS / "frames.yaml"),
        "--dry-run",
        "--no-estimate",
        "--profile",
        "paper",
        "--set",
        f"data.root={co3d.root}",
        "--set",
        "priors.depth_source=ground_truth",
    ]
    assert run.main(args) == 0
    out = capsys.readouterr().out
    assert "train.precision" not in out.split("protocol card:\n", 1)[1]
    # no GPU has measured pvcnn2: the dry run's GPU-hours are a bound, and say so (sweeps/plan/estimate.py)
    assert "paper-profile GPU-hours: not measured for model.denoiser=pvcnn2" in out
    assert "lower bound, not a measurement: ≥ " in " ".join(out.split())
    assert run.main([*args, "--set", "train.precision=fp32"]) == 0
    card = capsys.readouterr().out.split("protocol card:\n", 1)[1]
    assert f"deviation: {pc2}" in " ".join(card.split())  # the dry run folds lines at 120 columns


def test_table_5_cells_are_the_papers_co3d_cdm():
    for name in ("point_size", "frames", "frames_point_size"):
        for cell in expand(load_spec(SWEEPS / f"{name}.yaml"), "paper").cells:
            cfg = cell.config
            assert (cfg.priors.prior_2d, cfg.priors.render_kind, cfg.data.num_points) == ("depth", "depth", 16384), name


def test_a_table_of_two_data_sets_needs_data_kind_with_data_root(shapenet, capsys):
    with pytest.raises(SpecError, match="--set data.kind: this table ran on shapenet_r2n2 and co3d"):
        expand(load_spec(SWEEPS / "prior_type.yaml"), "paper", {"data.root": str(shapenet.root)})
    assert (
        run.main(
            [str(SWEEPS / "prior_type.yaml"), "--dry-run", "--profile", "paper", "--set", f"data.root={shapenet.root}"]
        )
        == 2
    )
    assert capsys.readouterr().err.startswith("error: --set data.kind:")


def test_the_card_travels_with_the_parent_run_into_the_report_and_the_results_table(tmp_path):
    """As sweeps/run.py starts a sweep: the card's lines tagged on the parent MLflow run (a real sqlite store);
    report.py reads them back and both results tables list them under the rows."""
    import json

    from sweeps.compare.table import build_table
    from sweeps.plan.protocol import CARD_TAG
    from sweeps.results.sweep import open_sweep, protocol_card_lines, results_table
    from sweeps.store.sweep_run import SweepRun

    spec_file = SWEEPS / "co3d.yaml"
    plan = expand(load_spec(spec_file), "smoke")
    lines = plan_card(plan).lines()
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = SweepRun.start(uri, plan.spec.name, "co3d · smoke",
                           tags={"spec": plan.spec.name, "profile": "smoke", CARD_TAG: "\n".join(lines)},
                           params={"trials": plan.num_trials, "steps": plan.profile.steps})
    plan_file = tmp_path / "plan.json"
    plan_file.write_text(json.dumps({"fixed": plan.fixed, "sets": {}, "cells": []}, default=str))
    sweep.log_artifacts([spec_file, plan_file])
    sweep.end()
    record_ = open_sweep(uri, plan.spec.name)
    assert protocol_card_lines(record_) == lines
    assert (
        lines[0]
        == "deviation: data set: the procedural data set stands in for Co3D v2; procedural bottle, mug and sofa "
        "stand in for hydrant, teddybear and toytruck"
    )
    theirs = results_table(record_, []).notes
    ours = build_table([], plan.spec.metric.name, plan.spec.metric.mode, "t", "", settings=table_settings(plan)).notes
    assert [n for n in theirs if n.startswith("protocol: ")] == [n for n in ours if n.startswith("protocol: ")] == [
        f"protocol: {line}" for line in lines]
