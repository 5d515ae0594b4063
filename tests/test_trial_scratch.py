"""A sweep's node-local scratch folder (``<TMPDIR>/cdm-trials-<uid>/<sweep>/``) goes when the sweep ends: only that
sweep's, never another's, and a link in it is removed, not followed."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from sweeps.execute.trial import remove_sweep_scratch, sweep_scratch, trial_scratch


@pytest.fixture
def outside(tmp_path, monkeypatch) -> Path:
    """A private temporary folder for the scratch, and a folder outside it holding one file, ``keep.txt``."""
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    folder = tmp_path / "outside"
    folder.mkdir()
    (folder / "keep.txt").write_text("kept")
    return folder


def _trial(sweep: str, trial_id: str) -> Path:
    """A trial's scratch folder as a trial leaves it: one evaluation file."""
    folder = trial_scratch(sweep, trial_id)
    (folder / "eval").mkdir(parents=True)
    (folder / "eval" / "cloud.ply").write_text("ply")
    return folder


def test_the_ended_sweeps_folder_goes_whole_and_another_sweeps_stays(outside):
    mine, other = _trial("/results/a/smoke", "a_00000"), _trial("/results/b/smoke", "b_00000")
    (mine / "link").symlink_to(outside)  # a link inside: removed, its target kept
    remove_sweep_scratch("/results/a/smoke", whole=True)
    assert not mine.parent.exists()
    assert (outside / "keep.txt").read_text() == "kept"
    assert (other / "eval" / "cloud.ply").read_text() == "ply"
    assert [p.name for p in mine.parent.parent.iterdir()] == [other.parent.name]


def test_train_workers_folders_stay_and_an_empty_sweep_folder_goes(outside):
    worker = _trial("/results/ddp/smoke", "d_00000")
    remove_sweep_scratch("/results/ddp/smoke", whole=False)  # a Train worker's folder stays on its node
    assert (worker / "eval" / "cloud.ply").read_text() == "ply"
    for path in (worker / "eval" / "cloud.ply", worker / "eval", worker):
        path.unlink() if path.is_file() else path.rmdir()
    remove_sweep_scratch("/results/ddp/smoke", whole=False)
    assert not worker.parent.exists()


def test_a_link_standing_for_the_sweeps_folder_is_not_followed(outside):
    link = sweep_scratch("/results/c/smoke")
    link.symlink_to(outside, target_is_directory=True)
    remove_sweep_scratch("/results/c/smoke", whole=True)
    assert (outside / "keep.txt").read_text() == "kept" and link.is_symlink()
