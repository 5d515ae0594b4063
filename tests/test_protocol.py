"""The protocol card: which deviations from the paper's protocol it lists, and where it is shown."""

from __future__ import annotations

from pathlib import Path

import pytest

from cdm.data.shapenet import SYNSETS
from sweeps import run
from sweeps.plan import expand
from sweeps.protocol import NO_DEVIATIONS, ProtocolCard, plan_card, protocol_card
from sweeps.spec import SpecError, load_spec
from tests.datasets_fixtures import make_co3d, make_shapenet

SWEEPS = Path(__file__).resolve().parent.parent / "sweeps"
ENCODER = "encoder: a small CNN trained from scratch (PC²: frozen ViT-S/16, 384 channels)"
DEPTH = "depth: the 2D depth prior reads ground-truth depth maps, an upper bound (the paper estimates depth)"


@pytest.fixture(scope="module")
def shapenet(tmp_path_factory):
    """All 13 R2N2 classes, BDM's split file, two views each: enough for a plan, not for training."""
    names = {name: synset for synset, name in SYNSETS.items()}
    return make_shapenet(tmp_path_factory.mktemp("sn13"), per_split={"train": 1, "val": 0, "test": 1}, views=2,
                         bdm_split=True, synsets=names)


@pytest.fixture(scope="module")
def co3d(tmp_path_factory):
    return make_co3d(tmp_path_factory.mktemp("co3d3"), categories=("hydrant", "teddybear", "toytruck"), frames=3,
                     splits={"train": 1, "val": 1, "test": 0})


def test_paper_profile_on_shapenet_lists_only_the_encoder(shapenet):
    plan = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper", {"data.root": str(shapenet.root)})
    assert {c.config.data.kind for c in plan.cells} == {"shapenet_r2n2"}
    assert sorted({c.config.data.categories[0] for c in plan.cells}) == sorted(SYNSETS.values())  # Table 1's 13
    assert plan.num_trials == 26 and all(c.paper for c in plan.cells)
    cfg = plan.cells[0].config
    assert (cfg.data.eval_split, cfg.eval.protocol, cfg.eval.normalise, cfg.diffusion.sampler, cfg.diffusion.clip_x0) == (
        "test", "paper", "reference", "ddpm", None)
    card = plan_card(plan)
    assert card.deviations == (ENCODER,)
    looser = protocol_card(cfg.replace(**{"eval.f1_threshold": 0.02})).deviations
    assert looser == ("metric: F1 at τ = 0.02 on the squared distance (BDM: 0.01)", ENCODER)
    assert card.notes == ("λ = 1 is ours: the paper gives no value for the 3D prior's weight",)


def test_paper_profile_on_co3d_lists_only_the_encoder_and_the_depth_source(co3d):
    plan = expand(load_spec(SWEEPS / "co3d.yaml"), "paper", {"data.root": str(co3d.root)})
    assert sorted(c.config.data.categories[0] for c in plan.cells) == ["hydrant", "hydrant", "teddybear", "teddybear",
                                                                      "toytruck", "toytruck"]
    assert {(c.config.data.num_points, c.config.eval.num_points) for c in plan.cells} == {(16384, 16384)}
    assert plan_card(plan).deviations == (ENCODER, DEPTH)
    pc2 = next(c for c in plan.cells if c.name.startswith("PC²"))
    assert protocol_card(pc2.config).deviations == (ENCODER,)  # no depth prior, no depth deviation


def test_shapenet_without_bdms_split_file_and_small_profiles_say_so(shapenet, tmp_path):
    bare = make_shapenet(tmp_path / "bare", per_split={"train": 1, "test": 1}, views=2)
    plan = expand(load_spec(SWEEPS / "prior_type.yaml"), "paper", {"data.root": str(bare.root), "data.kind": "shapenet_r2n2"})
    assert any(d.startswith("split: PC15k's test folders, not BDM's R2N2 test split") for d in plan_card(plan).deviations)
    assert {c.config.priors.render_kind for c in plan.cells} == {"planar"}  # Table 6's ShapeNet cells
    local = plan_card(expand(load_spec(SWEEPS / "point_size.yaml"), "local"))
    text = "\n".join(local.deviations)
    for aspect in ("data set: the procedural data set stands in", "objects: the first 16 held-out objects per category",
                   "normalisation: per-shape bounding box", "points: 512 per cloud, 512 scored (the reference: 4096)",
                   "sampler: DDIM over 10 steps, trailing spacing, x̂₀ clipped to ±1", "diffusion: x0-prediction (paper: ε)",
                   "training: 1,800 steps (PC²: 100,000), batch 4 (paper: 8), 64² images (paper: 224²), AdamW lr 0.001, "
                   "betas (0.9, 0.99), 150 warm-up steps (PC²: 1e-3, (0.95, 0.999), 2,000)", ENCODER):
        assert aspect in text, aspect
    assert not local.faithful and NO_DEVIATIONS not in local.lines()
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


def test_depth_renders_that_average_surfaces_are_a_deviation():
    cfg = expand(load_spec(SWEEPS / "point_size.yaml"), "paper").cells[0].config
    assert not any(d.startswith("3D prior:") for d in protocol_card(cfg).deviations)  # the front layer, as PyTorch3D
    averaged = protocol_card(cfg.replace(**{"priors.depth_layer": None})).deviations
    assert "3D prior: depth renders average front and back surfaces (the paper's PyTorch3D z-buffer keeps the nearest)" in averaged


def test_table_5_cells_are_the_papers_co3d_cdm():
    for name in ("point_size", "frames", "frames_point_size"):
        for cell in expand(load_spec(SWEEPS / f"{name}.yaml"), "paper").cells:
            cfg = cell.config
            assert (cfg.priors.prior_2d, cfg.priors.render_kind, cfg.data.num_points) == ("depth", "depth", 16384), name


def test_a_table_of_two_data_sets_needs_data_kind_with_data_root(shapenet, capsys):
    with pytest.raises(SpecError, match="--set data.kind: this table ran on shapenet_r2n2 and co3d"):
        expand(load_spec(SWEEPS / "prior_type.yaml"), "paper", {"data.root": str(shapenet.root)})
    assert run.main([str(SWEEPS / "prior_type.yaml"), "--dry-run", "--profile", "paper", "--set", f"data.root={shapenet.root}"]) == 2
    assert capsys.readouterr().err.startswith("error: --set data.kind:")


def test_dry_run_prints_the_card(shapenet, capsys):
    assert run.main([str(SWEEPS / "shapenet.yaml"), "--dry-run", "--no-estimate", "--profile", "paper",
                     "--set", f"data.root={shapenet.root}"]) == 0
    out = capsys.readouterr().out
    card = out.split("protocol card:\n", 1)[1].splitlines()[:2]
    assert card == [f"  deviation: {ENCODER}", "  note: λ = 1 is ours: the paper gives no value for the 3D prior's weight"]


def test_the_card_travels_with_the_parent_run_into_the_report_and_the_results_table(tmp_path):
    """As sweeps/run.py starts a sweep: the card's lines tagged on the parent MLflow run (a real sqlite store);
    report.py reads them back and both results tables list them under the rows."""
    import json

    from sweeps import report
    from sweeps.protocol import CARD_TAG
    from sweeps.results import build_table
    from sweeps.tracking import SweepRun

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
    record = report.open_sweep(uri, plan.spec.name)
    assert report.protocol_card_lines(record) == lines
    assert lines[0] == "deviation: data set: the procedural data set stands in for Co3D v2; procedural bottle, mug and sofa stand in for hydrant, teddybear and toytruck"
    theirs = report.results_table(record, []).notes
    ours = build_table([], plan.spec.metric.name, plan.spec.metric.mode, "t", "", settings=run._settings(plan)).notes
    assert [n for n in theirs if n.startswith("protocol: ")] == [n for n in ours if n.startswith("protocol: ")] == [
        f"protocol: {line}" for line in lines]
