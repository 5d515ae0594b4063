"""sweeps/rerun.py: every value read back from a recorded child run is checked before it is used."""

from __future__ import annotations

import pytest
from mlflow import MlflowClient

from cdm.provenance import installed_packages, machine_record
from sweeps.rerun import RerunError, machine_differences, rerun
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


def test_the_rerun_names_each_part_of_the_machine_that_differs_and_which_packages(store, tmp_path):
    here = machine_record()
    same = {f"repro.{k}": v for k, v in here.items()}
    uri, run = _recorded(store, tmp_path, same)
    client = MlflowClient(uri)
    assert machine_differences(client, run, client.get_run(run).data.tags) == []

    recorded = installed_packages()
    numpy = next(i for i, line in enumerate(recorded) if line.startswith("numpy=="))
    recorded[numpy] = "numpy==0.1"
    gone = recorded.pop(0)  # installed here, absent from the record
    recorded.append("zz-only-recorded==1.0")
    (tmp_path / "packages.txt").write_text("\n".join(recorded) + "\n")
    capability = "AVX2" if here["cpu_capability"] != "AVX2" else "DEFAULT"
    other = {**same, "repro.cpu_model": "AMD EPYC 7B13 64-Core Processor", "repro.cpu_capability": capability,
             "repro.packages_digest": "0" * 16}
    uri, run = _recorded(store, tmp_path, other)
    client.log_artifact(run, str(tmp_path / "packages.txt"), "environment")
    lines = machine_differences(client, run, client.get_run(run).data.tags)
    name, _, ver = gone.partition("==")
    assert lines == [
        f"repro.cpu_model: recorded AMD EPYC 7B13 64-Core Processor, here {here['cpu_model']}",
        f"repro.cpu_capability: recorded {capability}, here {here['cpu_capability']}",
        f"repro.packages_digest: recorded {'0' * 16}, here {here['packages_digest']}",
        f"packages: numpy 0.1 → {_installed('numpy')}, +{name} {ver} (only here), "
        "-zz-only-recorded 1.0 (only recorded)",
    ]

    uri, run = _recorded(store, tmp_path, {"repro.cpu_model": "a\nplanted line"})
    lines = machine_differences(client, run, client.get_run(run).data.tags)
    assert lines[0].startswith("repro.cpu_model: recorded 'a\\nplanted line', here ") and "\n" not in "".join(lines)

    uri, run = _recorded(store, tmp_path, {})  # a run from before the machine was recorded
    assert machine_differences(client, run, client.get_run(run).data.tags) == [
        f"the record names no machine (a run from before it was recorded); this one: {here['cpu_model']}, "
        f"{here['cpu_capability']}, {here['math_libraries']}"]


def _installed(name: str) -> str:
    return next(line.partition("==")[2] for line in installed_packages() if line.startswith(name + "=="))
