"""sweeps/results/rerun.py: every value read back from a recorded child run is checked before it is used."""

from __future__ import annotations

import pytest
from mlflow import MlflowClient

from sweeps.results.rerun import RerunError, rerun
from tests.hostile_files import ROOT, assert_refused, run_command


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """One MLflow store for the module (a SQLite store's first open costs seconds), with a parent run."""
    folder = tmp_path_factory.mktemp("store")
    uri = f"sqlite:///{folder}/mlflow.db"
    client = MlflowClient(uri)
    experiment = client.create_experiment("e")
    return uri, experiment, client.create_run(experiment).info.run_id


def _recorded(store, tmp_path, tags: dict[str, str], config: str | None = "train:\n  steps: 2\n") -> tuple[str, str]:
    """A child run as a sweep trial leaves it (repro.* tags, config.yaml), with ``tags`` over the record."""
    uri, experiment, parent = store
    client = MlflowClient(uri)
    run = client.create_run(
        experiment,
        tags={
            "mlflow.parentRunId": parent,
            "trial_id": "t0",
            "repro.config_hash": "0" * 12,
            "repro.git_commit": "abc",
            "repro.git_dirty": "false",
            **tags,
        },
    ).info.run_id
    if config is not None:
        (tmp_path / "config.yaml").write_text(config)
        client.log_artifact(run, str(tmp_path / "config.yaml"))
    client.set_terminated(run)
    return uri, run


@pytest.mark.parametrize("threads", ["0", "-1", "²", "9" * 5001, "4097", "two"])
def test_a_recorded_thread_count_out_of_range_is_refused_before_training(store, tmp_path, threads):
    uri, run = _recorded(store, tmp_path, {"repro.torch_threads": threads})
    with pytest.raises(
        RerunError, match=r"repro.torch_threads is .*; expected a whole number from 1 to 4096"
    ) as refused:
        rerun(run, uri, tmp_path / "reruns", force=True)
    assert "\n" not in str(refused.value)
    assert not (tmp_path / "reruns").exists()


@pytest.mark.parametrize(("config", "said"), [(None, "has no readable config.yaml"),
                                              ("[" * 100_000 + "]" * 100_000, "nested 100000 deep; at most 64"),
                                              ("data:\n  num_points: ²\n", "data.num_points")])
def test_a_missing_or_damaged_recorded_config_is_refused_in_one_line(store, tmp_path, config, said):
    uri, run = _recorded(store, tmp_path, {"repro.torch_threads": "1"}, config)
    with pytest.raises(RerunError, match=said) as refused:
        rerun(run, uri, tmp_path / "reruns", force=True)
    assert "\n" not in str(refused.value)


def test_a_recorded_commit_with_a_newline_is_shown_on_one_line(store, tmp_path):
    uri, run = _recorded(store, tmp_path, {"repro.torch_threads": "1", "repro.git_commit": "abc\nerror: planted"})
    with pytest.raises(RerunError, match=r"^recorded commit 'abc\\nerror: planted', checked out") as refused:
        rerun(run, uri, tmp_path / "reruns")
    assert "\n" not in str(refused.value)


@pytest.mark.slow
def test_rerun_force_of_a_record_with_torch_threads_0_exits_2_through_the_command(store, tmp_path):
    uri, run = _recorded(store, tmp_path, {"repro.torch_threads": "0"})
    outcome = run_command([str(ROOT / "sweeps" / "rerun.py"), run, "--force", "--tracking-uri", uri,
                           "--out", str(tmp_path / "results")], tmp_path, timeout=300)
    assert_refused(outcome, "repro.torch_threads is '0'")
    assert not (tmp_path / "results").exists()
