"""``python -m cdm train`` against a damaged resume file and a planted out_dir (issue 55 §3): a hostile
optimiser, scheduler or RNG state is one ``error:`` line naming the file, exit 2, nothing trained; a link in
``train.out_dir`` never makes train write or remove anything outside it."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml

from cdm.checkpoint import CHECKPOINT_FILE, Checkpoint, load_checkpoint, save_checkpoint
from tests.conftest import TINY
from tests.hostile_files import Outcome, assert_refused, run_command

pytestmark = pytest.mark.slow


def _train(tmp_path: Path, out: Path, *args: str, steps: int = 2, every: int = 2) -> Outcome:
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY))
    sets = {"train.steps": steps, "train.eval_every": every, "train.out_dir": out}
    return run_command(["-m", "cdm", "train", "--config", str(config), *args,
                        *[a for k, v in sets.items() for a in ("--set", f"{k}={v}")]], tmp_path, timeout=300)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, dict]:
    """A 2-step run's checkpoint folder and its contents."""
    tmp = tmp_path_factory.mktemp("run")
    done = _train(tmp, tmp / "run")
    assert done.code == 0, done.stderr[-2000:]
    folder = tmp / "run" / "checkpoints" / "step_0000002"
    return folder, vars(load_checkpoint(folder))


def _first_group(state: dict) -> dict:
    return state["optimizer"]["param_groups"][0]


def _state_of(index: int):
    return lambda state: state["optimizer"]["state"][index]


CASES = {  # name: (how the checkpoint is damaged, what the one line says)
    "nan_lr": (lambda s: _first_group(s).update(lr=math.nan),
               "its optimizer['param_groups'][0]['lr'] is nan, not a finite float ≥ 0"),
    "params": (lambda s: _first_group(s).update(params=_first_group(s)["params"][::-1]),
               "its optimizer['param_groups'][0]['params'] is [53, 52,"),
    "param_count": (lambda s: _first_group(s).update(params=[0, 1]), "['params'] is a list of 2, not a list of 54"),
    "flag": (lambda s: _first_group(s).update(fused=False), "['fused'] is False; this run's is True"),
    "moment_shape": (lambda s: _state_of(0)(s).update(exp_avg=torch.zeros(1)),
                     "its optimizer's state[0]['exp_avg'] is a torch.float32 tensor of shape (1,), not a"),
    "negative": (lambda s: _state_of(0)(s).update(exp_avg_sq=-_state_of(0)(s)["exp_avg_sq"] - 1),
                 "its optimizer's state[0]['exp_avg_sq'] holds a negative second moment"),
    "index": (lambda s: s["optimizer"]["state"].update({10**6: {}}), "its optimizer's state is not keyed by"),
    "no_optimizer": (lambda s: s.update(optimizer=None), "its optimizer is None, not an optimizer's state dict"),
    "scheduler_key": (lambda s: s["scheduler"].update(optimizer=0), "its scheduler is ["),
    "lambda_state": (lambda s: s["scheduler"].update(lr_lambdas=[{"__doc__": "x"}]),
                     "its scheduler['lr_lambdas'][0] is a dict; this run's is None"),
    "scheduler_epoch": (lambda s: s["scheduler"].update(last_epoch=-5),
                        "its scheduler['last_epoch'] is -5, not an int ≥ 0"),
    "generator": (lambda s: s.update(generator=torch.zeros(3, dtype=torch.uint8)),
                  "its noise generator state is a torch.uint8 tensor of shape (3,)"),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_hostile_optimiser_or_scheduler_is_one_line_naming_the_file_and_trains_nothing(trained, tmp_path, name):
    folder, state = trained
    damage, message = CASES[name]
    changed = {**state, "optimizer": _copy(state["optimizer"]), "scheduler": _copy(state["scheduler"])}
    damage(changed)
    file = tmp_path / "resume" / CHECKPOINT_FILE
    save_checkpoint(Checkpoint(**changed), file.parent)
    outcome = _train(tmp_path, tmp_path / "out", "--resume-from", str(file.parent), steps=4)
    assert_refused(outcome, f"error: resume: {file}: ", message)
    assert not (tmp_path / "out" / "checkpoints").exists() and "step 3" not in outcome.stdout


def _copy(value):
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value.clone() if isinstance(value, torch.Tensor) else value


def test_the_undamaged_checkpoint_resumes(trained, tmp_path):
    """The control of the cases above: the same file, undamaged, continues to step 4."""
    folder, _ = trained
    outcome = _train(tmp_path, tmp_path / "out", "--resume-from", str(folder), steps=4)
    assert outcome.code == 0 and "done at step 4" in outcome.stdout, outcome.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "out" / "checkpoints").iterdir()) == ["step_0000004"]


def _outside(tmp_path: Path) -> tuple[Path, dict[str, bytes]]:
    """A folder outside the run holding a file, as a neighbour's data would."""
    outside = tmp_path / "elsewhere"
    (outside / "step_0000001").mkdir(parents=True)
    (outside / "precious.txt").write_bytes(b"someone's data\n")
    (outside / "step_0000001" / CHECKPOINT_FILE).write_bytes(b"someone's checkpoint\n")
    return outside, _listing(outside)


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else b"" for p in sorted(folder.rglob("*"))}


@pytest.mark.parametrize("planted", ["checkpoints", "eval"])
def test_a_folder_link_in_out_dir_is_refused_before_the_first_step(tmp_path, planted):
    outside, before = _outside(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / planted).symlink_to(outside, target_is_directory=True)
    outcome = _train(tmp_path, out)
    assert_refused(outcome, f"train.out_dir: {out / planted} would be written to {outside}, outside {out}")
    assert _listing(outside) == before and "step 1" not in outcome.stdout


@pytest.mark.parametrize("planted", [".tmp_step_0000002", "step_0000002"])
def test_a_link_where_a_step_folder_goes_is_refused_and_not_followed(tmp_path, planted):
    outside, before = _outside(tmp_path)
    out = tmp_path / "out"
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / planted).symlink_to(outside, target_is_directory=True)
    outcome = _train(tmp_path, out)
    assert_refused(outcome, f"train.out_dir: {out / 'checkpoints' / planted} is a symbolic link where train keeps "
                            "its checkpoints; remove it")
    assert _listing(outside) == before and (out / "checkpoints" / planted).is_symlink()


def test_the_cleanup_of_old_steps_removes_only_this_runs_own_folders(tmp_path):
    outside, before = _outside(tmp_path)
    out = tmp_path / "out"
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "step_0000000").symlink_to(outside, target_is_directory=True)
    (out / "checkpoints" / "step_9999999").mkdir()  # planted later step: neither counted nor removed
    outcome = _train(tmp_path, out, steps=3, every=1)
    assert outcome.code == 0 and "done at step 3" in outcome.stdout, outcome.stderr[-2000:]
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == [
        "step_0000000", "step_0000002", "step_0000003", "step_9999999"]
    assert _listing(outside) == before and (out / "checkpoints" / "step_0000000").is_symlink()
