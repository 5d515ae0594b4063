"""Caps and boundary checks of a sweep (sweeps/plan/limits.py, sweeps/store/, claim.py), each bad input tried
through ``sweeps/run.py`` too: exit 2, one ``error:`` line naming the field or file, nothing written,
Ray never started."""

from __future__ import annotations

import math
import subprocess
import sys
import time
import tracemalloc
import typing
from pathlib import Path

import pytest
import ray

from cdm import lab
from cdm.config import Config, ConfigError, config_field_paths, load_config
from cdm.memory import check_memory, estimate_train_bytes
from sweeps import run
from sweeps.execute.claim import ClaimError, claim
from sweeps.plan.limits import LimitError, check_trials
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import Spec, load_spec
from sweeps.plan.trials import expand
from sweeps.store.files import StoreError, check_storage, parse_state
from sweeps.store.tracking import check_tracking_uri
from tests.hostile_files import YAML_BOMB

ROOT = Path(__file__).resolve().parents[1]

def _grid(values_per_key: int, keys: int = 3) -> str:
    fields = ["priors.point_size", "priors.lambda_3d", "train.lr"][:keys]
    return "name: big\ngrid:\n" + "".join(
        f"  {k}: [{', '.join(f'{0.001 * (i + 1):.3f}' for i in range(values_per_key))}]\n" for k in fields)


def test_trial_cap_counts_without_building_and_is_raised_by_the_flag(tmp_path):
    (tmp_path / "big.yaml").write_text(_grid(100))
    spec = load_spec(tmp_path / "big.yaml")
    t0 = time.perf_counter()
    with pytest.raises(LimitError, match="1000000 trials.*--max-cells 1000000"):
        check_trials(spec)
    assert time.perf_counter() - t0 < 1.0
    check_trials(spec, 10**6)
    small = Spec.model_validate({"name": "s", "grid": {"priors.point_size": [0.01, 0.02]}, "seeds": [0, 1, 2]})
    check_trials(small, 6)
    with pytest.raises(LimitError, match="6 trials"):
        check_trials(small, 5)
    optuna = Spec.model_validate({"name": "o", "search": {"kind": "optuna", "num_samples": 8, "space": {
        "priors.lambda_3d": {"type": "float", "low": 0.1, "high": 1.0}}}, "profiles": {"paper": {"num_samples": 2000}}})
    with pytest.raises(LimitError, match="search.num_samples: 2000 trials"):
        check_trials(optuna)


def test_a_dry_run_past_the_listed_trials_checks_each_cell_in_small_memory(tmp_path, monkeypatch, capsys):
    import torch  # noqa: F401  (imported before measuring: the dry-run's own allocations are what counts)

    from sweeps.plan import limits, request

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(request, "LISTED_TRIALS", 20)
    monkeypatch.setattr(limits, "PROGRESS_EVERY", 250)
    (tmp_path / "big.yaml").write_text(_grid(10, keys=3))  # 1,000 cells: 10⁶ held 2.9 GB at about 3 kB each
    spec = load_spec(tmp_path / "big.yaml")
    expand(spec, "smoke", keep=1)  # imports and caches
    tracemalloc.start()
    held = expand(spec, "smoke")
    whole = tracemalloc.get_traced_memory()[1]
    del held
    tracemalloc.reset_peak()
    start = tracemalloc.get_traced_memory()[0]
    capsys.readouterr()
    assert run.main(["big.yaml", "--smoke", "--dry-run", "--max-cells", "1000"]) == 0
    streamed = tracemalloc.get_traced_memory()[1] - start
    tracemalloc.stop()
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "checking up to 1000 trials one at a time (listing the first 20) …"  # before any cell is built
    assert [line for line in out if "checked" in line and "/1000" in line] == [
        f"  checked {i}/1000 trials …" for i in (250, 500, 750, 1000)]  # a line per 250 cells of work
    listed = [line for line in out if line.startswith("   ") and ". " in line[:8]]
    assert len(listed) == 20 and listed[-1].startswith("   20. ")
    assert any(line.startswith("  … and 980 more trials, each checked") for line in out) and out[-1].startswith(
        "estimate: none for a dry-run"
    )
    assert whole > 5 * 2**20 and streamed < whole / 10, (whole, streamed)
    text = _grid(10, keys=3)
    (tmp_path / "bad.yaml").write_text(text[:text.rindex("0.010")] + "-1]\n")  # the 10th cell, past the one kept
    with pytest.raises(
        SpecError, match="cell point_size=0.001 · λ=0.001 · lr=-1: train.lr: Input should be greater than 0"
    ):
        expand(load_spec(tmp_path / "bad.yaml"), "smoke", keep=1)


def _annotation(path: str):
    model = Config
    *groups, name = path.split(".")
    for group in groups:
        model = model.model_fields[group].annotation
    return model.model_fields[name].annotation


def test_every_float_field_must_be_finite():
    floats = [k for k in config_field_paths() if _annotation(k) is float
              or (typing.get_origin(_annotation(k)) is not tuple and float in typing.get_args(_annotation(k)))]
    assert "train.ema_decay" in floats and "priors.lambda_3d" in floats and len(floats) >= 12  # betas: below
    for key in floats:
        for bad in (math.inf, -math.inf, math.nan):
            with pytest.raises(ConfigError, match=f"{key}: Input should be a finite number"):
                load_config(None, {key: bad})
    with pytest.raises(ConfigError, match="train.betas.1: Input should be a finite number"):
        load_config(None, {"train.betas": [0.9, math.nan]})
    with pytest.raises(ValueError, match="finite number"):
        Spec.model_validate(
            {"name": "s", "grid": {"priors.point_size": [0.01]}, "resources": {"cpus_per_worker": math.inf}}
        )


def test_memory_estimate_grows_with_each_size_and_refuses_past_the_machine():
    base = expand(load_spec(ROOT / "sweeps" / "point_size.yaml"), "smoke").cells[0].config
    b0 = estimate_train_bytes(base, 2)
    # One more object per split and category costs one index entry per category.
    more = load_config(None, {**base.flat(), "data.train_objects": base.data.train_objects + 1})
    assert estimate_train_bytes(more, 2) - b0 == 2 * 256
    # Doubling the batch adds exactly one batch's worth: the part that scales with train.batch_size.
    double = load_config(None, {**base.flat(), "train.batch_size": 2 * base.train.batch_size})
    fixed = (base.data.train_objects + base.data.val_objects) * 2 * 256 + 2 * 512 * 2**20
    assert estimate_train_bytes(double, 2) - b0 == b0 - fixed
    check_memory([base], concurrent=2)  # the smoke profile fits any machine
    huge = load_config(None, {**base.flat(), "data.train_objects": 10**11})
    with pytest.raises(
        ConfigError, match=r"data.train_objects=100000000000.*need at least .* GiB but this machine has 16.0 GiB"
    ):
        check_memory([huge], concurrent=1, total=16 * 2**30)


def test_state_file_tracking_uri_and_storage_checks(tmp_path):
    for text, needle in [
        ("[]", "a JSON list, not an object"),
        ("\ufffd\x00", "not JSON"),
        ('{"spec": {}, "sets": {}, "profile": "smoke", "tracking_uri": "sqlite:///x"}', "parent_run_id"),
    ]:
        with pytest.raises(StoreError, match=needle):
            parse_state(text.encode(), "sweep.json")
    with pytest.raises(StoreError, match="unsupported scheme 'ftp'"):
        check_tracking_uri("ftp://nope")
    with pytest.raises(StoreError, match="no MLflow server answers"):
        check_tracking_uri("http://127.0.0.1:9")  # the discard port: nothing listens
    check_tracking_uri(f"sqlite:///{tmp_path}/sub/mlflow.db")
    (tmp_path / "file").write_text("")
    with pytest.raises(StoreError, match="is a file, not a folder"):
        check_storage(str(tmp_path / "file" / "spec" / "smoke"))
    with pytest.raises(StoreError, match="cannot write in /proc"):
        check_storage("/proc/cdm-results/spec/smoke")
    check_storage(str(tmp_path / "results" / "spec" / "smoke"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]  # the checks wrote nothing


def _hold(folder: str) -> subprocess.Popen:
    """Another process claiming ``folder`` and noting a parent run; it prints once it holds the claim."""
    code = (f"import sys, time; from sweeps.execute.claim import claim; c = claim({folder!r}); "
            "c.record('sqlite:////somewhere/mlflow.db', 'abc123'); print('held', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_claim_is_exclusive_across_processes_and_dies_with_its_holder(tmp_path):
    folder = str(tmp_path / "results" / "spec" / "smoke")
    holder = _hold(folder)
    try:
        with pytest.raises(ClaimError, match=f"process {holder.pid} .*parent run is abc123 in sqlite:////somewhere"):
            claim(folder)
    finally:
        holder.kill()
        holder.wait()
    held = claim(folder)  # SIGKILL released it: no stale claim
    held.release()


def test_a_released_claim_leaves_only_what_the_sweep_wrote(tmp_path):
    folder = tmp_path / "results" / "spec" / "smoke"
    held = claim(str(folder))
    assert (tmp_path / "results" / "spec" / ".smoke.lock").is_file()
    held.release()
    assert list(tmp_path.iterdir()) == []  # nothing written in it: the lock file and its new folders go
    held.release()  # a second release does nothing
    held = claim(str(folder))
    folder.mkdir()
    (folder / "sweep.json").write_text("{}")
    held.release()
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == [
        "results", "results/spec", "results/spec/smoke", "results/spec/smoke/sweep.json"]
    claim(str(folder)).release()  # the next copy claims it again


BAD_SPECS = {
    "binary": (b"\x89PNG\r\n\x1a\n\x00\x00", [], "not UTF-8 text"),
    "bomb": (YAML_BOMB.encode(), [], "expand to more than"),
    "grid": (_grid(100).encode(), ["--dry-run"], "1000000 trials"),
    "inf": (
        b"name: s\ngrid: {priors.point_size: [0.04]}\n",
        ["--set", "priors.lambda_3d=.inf"],
        "priors.lambda_3d: Input should be a finite",
    ),
    "objects": (
        b"name: s\ngrid: {priors.point_size: [0.04]}\n",
        ["--set", "data.train_objects=100000000000", "--dry-run"],
        "data.train_objects=100000000000",
    ),
    "ftp": (
        b"name: s\ngrid: {priors.point_size: [0.04]}\n",
        ["--tracking-uri", "ftp://nope"],
        "--tracking-uri ftp://nope",
    ),
    "storage": (
        b"name: s\ngrid: {priors.point_size: [0.04]}\n",
        ["--out", "/proc/cdm-results"],
        "--out /proc/cdm-results",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_SPECS))
def test_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch, case):
    data, extra, needle = BAD_SPECS[case]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.yaml").write_bytes(data)
    argv = ["spec.yaml", "--smoke", "--out", "results", "--tracking-uri", f"sqlite:///{tmp_path}/mlflow.db", *extra]
    assert run.main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]
    assert not ray.is_initialized()


@pytest.mark.parametrize("content,needle", [(b"[]", "a JSON list"), (b"\xff\xfe\x00garbage", "not JSON"),
                                            (b'{"spec": 1}', "spec: expected a JSON object")])
def test_damaged_state_file_on_resume(tmp_path, capsys, monkeypatch, content, needle):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.yaml").write_text("name: s\ngrid: {priors.point_size: [0.04]}\n")
    folder = tmp_path / "results" / "s" / "smoke"
    folder.mkdir(parents=True)
    (folder / "sweep.json").write_bytes(content)
    assert run.main(["spec.yaml", "--smoke", "--out", "results", "--resume"]) == 2
    err = capsys.readouterr().err
    assert needle in err and str(folder / "sweep.json") in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in folder.iterdir()) == ["sweep.json"] and not (tmp_path / "mlflow.db").exists()


def test_a_claimed_folder_is_refused_naming_the_running_parent_run(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.yaml").write_text("name: s\ngrid: {priors.point_size: [0.04]}\n")
    holder = _hold(str(tmp_path / "results" / "s" / "smoke"))
    try:
        assert (
            run.main(["spec.yaml", "--smoke", "--out", "results", "--tracking-uri", f"sqlite:///{tmp_path}/m.db"])
            == 2
        )
    finally:
        holder.kill()
        holder.wait()
    err = capsys.readouterr().err
    assert "a sweep is already running there" in err and "parent run is abc123" in err, err
    assert not ray.is_initialized() and not (tmp_path / "results" / "s" / "smoke").exists()


@pytest.mark.parametrize("command", ["report", "rerun"])
def test_report_and_rerun_refuse_a_bad_tracking_uri(tmp_path, capsys, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    assert lab.main([command, "abc", "--tracking-uri", "ftp://nope"]) == 2
    err = capsys.readouterr().err
    assert "unsupported scheme 'ftp'" in err and len(err.strip().splitlines()) == 1, err
    assert not list(tmp_path.iterdir())
