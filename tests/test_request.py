"""The sweep request: the command line's arguments checked and turned into the plan before Ray starts."""

from __future__ import annotations

import json

import pytest

from sweeps import run
from sweeps.plan.request import RequestError, plan_request

SPEC = "name: s\ngrid: {priors.point_size: [0.02, 0.04]}\n"


def _args(tmp_path, *extra):
    (tmp_path / "s.yaml").write_text(SPEC)
    return run.build_parser().parse_args([str(tmp_path / "s.yaml"), "--smoke", "--out", str(tmp_path / "r"), *extra])


def test_a_request_plans_every_trial_and_says_where_the_sweep_is_kept(tmp_path):
    request = plan_request(_args(tmp_path, "--set", "priors.num_views=3"))
    assert request.sweep_dir == str(tmp_path / "r" / "s" / "smoke")
    assert request.state_file == f"{request.sweep_dir}/sweep.json" and request.state is None
    assert [c.config.priors.point_size for c in request.plan.cells] == [0.02, 0.04]
    assert {c.config.priors.num_views for c in request.plan.cells} == {3} and request.sets == {"priors.num_views": 3}
    assert (request.budget, request.remote) == (None, False)
    assert not (tmp_path / "r").exists()  # a plan writes nothing


def test_resume_plans_the_spec_and_sets_the_sweep_started_with_and_names_a_damaged_state(tmp_path):
    folder = tmp_path / "r" / "s" / "smoke"
    folder.mkdir(parents=True)
    started = {"spec": {"name": "s", "grid": {"priors.point_size": [0.08]}}, "sets": {"priors.num_views": 2},
               "profile": "smoke", "budget": None, "tracking_uri": "sqlite:///x.db", "parent_run_id": "p"}
    (folder / "sweep.json").write_text(json.dumps(started))
    request = plan_request(_args(tmp_path, "--resume"))  # the file says 0.02 and 0.04 now: the sweep keeps 0.08
    assert [(c.config.priors.point_size, c.config.priors.num_views) for c in request.plan.cells] == [(0.08, 2)]
    assert request.state == started
    (folder / "sweep.json").write_text(json.dumps({**started, "spec": {"name": "s", "grid": {"priors.nope": [1]}}}))
    with pytest.raises(RequestError, match=r"--resume: .*sweep.json is damaged \(.*\); remove the folder"):
        plan_request(_args(tmp_path, "--resume"))


def test_a_dry_run_says_where_the_results_and_the_mlflow_runs_will_go(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    args = [str(tmp_path / "s.yaml"), "--smoke", "--dry-run", "--no-estimate"]
    (tmp_path / "s.yaml").write_text(SPEC)
    assert run.main(args) == 0
    out = capsys.readouterr().out
    folded = " ".join(out.split())  # lines folded at 120 bytes, joined
    assert (f"storage: {tmp_path / 'results' / 's' / 'smoke'} (results.md, results.csv, the trials' folders and "
            "checkpoints, Tune's state)") in folded
    assert (f"MLflow tracking URI: sqlite:///{tmp_path / 'mlflow.db'}, experiment s "
            f"(artifacts: {tmp_path / 'mlruns' / 's'})") in folded
    assert max(len(line.encode()) for line in out.splitlines()) <= 120
    # A resumed sweep logs into the store it started with (sweep.json), whatever the environment says.
    folder = tmp_path / "r" / "s" / "smoke"
    folder.mkdir(parents=True)
    (folder / "sweep.json").write_text(json.dumps({
        "spec": {"name": "s", "grid": {"priors.point_size": [0.08]}}, "sets": {}, "profile": "smoke", "budget": None,
        "tracking_uri": "http://127.0.0.1:5999", "parent_run_id": "p"}))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///elsewhere.db")
    assert run.main([*args, "--resume", "--out", str(tmp_path / "r")]) == 0
    folded = " ".join(capsys.readouterr().out.split())
    assert f"storage: {folder} (" in folded
    assert "MLflow tracking URI: http://127.0.0.1:5999, experiment s (artifacts: the server's store)" in folded
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r", "s.yaml"]  # a dry run writes nothing
