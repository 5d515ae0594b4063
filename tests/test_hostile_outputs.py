"""Nothing deleted or written outside what a command made (issue #49, section 2), each case through the
command a user types: ``prepare`` fills only a new, empty or its own ``--out`` and removes only its own
scratch files; every tool writes through :func:`cdm.io.write.write_atomic`, so a link planted where it
writes is refused and its target left as it was.

Also from section 4, numbers and names read back: a 5,001-digit integer in a config or spec file, and a
crop named ``².png``, are named in one line.

Each subprocess costs ~3 s of interpreter start: four cases run in the fast tier, the rest are marked
slow; the depth tool's cases need ``transformers``."""

from __future__ import annotations

import json
import os
import stat

import pytest

from cdm.data.cache import MANIFEST, SCRATCH
from tests.datasets_fixtures import make_co3d
from tests.hostile_files import ROOT, assert_refused, run_command

FOREIGN = ".notes.tmp-2026"
"""Another program's file whose name looks like a temporary one: prepare once deleted every such name."""


@pytest.fixture(scope="module")
def co3d(tmp_path_factory):
    root = tmp_path_factory.mktemp("co3d")
    make_co3d(root, categories=("teddybear",), frames=2, splits={"train": 1, "val": 1})
    return root


def _prepare(root, out, cwd, *command, env=None):
    command = command or ("-m", "cdm", "prepare")
    return run_command([*command, "--set", "data.kind=co3d", "--root", str(root), "--out", str(out),
                        "--set", "data.image_size=32"], cwd, env=env)


def _foreign_folder(folder):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / FOREIGN).write_text("mine")
    return folder / FOREIGN


@pytest.mark.parametrize("command", [("-m", "cdm", "prepare"), pytest.param(
    (str(ROOT / "sweeps" / "inputs.py"), "prepare"), marks=pytest.mark.slow)])
def test_prepare_refuses_a_folder_of_other_files_and_removes_nothing(co3d, tmp_path, command):
    notes = _foreign_folder(tmp_path / "notes")
    outcome = _prepare(co3d, tmp_path / "notes", tmp_path, *command)
    assert_refused(outcome, f"--out: {tmp_path / 'notes'} holds files and no {MANIFEST}")
    assert notes.read_text() == "mine" and sorted(p.name for p in notes.parent.iterdir()) == [FOREIGN]


@pytest.mark.parametrize("where", [pytest.param("root", marks=pytest.mark.slow), "home",
                                   pytest.param("project", marks=pytest.mark.slow)])
def test_prepare_refuses_the_root_the_home_folder_and_the_project(co3d, tmp_path, where):
    home = tmp_path / "home"
    notes = _foreign_folder(home)
    out = {"root": "/", "home": "~", "project": str(ROOT)}[where]
    said = {"root": "the file system's root", "home": "the home folder", "project": "this project's folder"}[where]
    outcome = _prepare(co3d, out, tmp_path, env={"HOME": str(home)})
    assert_refused(outcome, f"--out: {out if where != 'home' else home} is {said}")
    assert notes.read_text() == "mine" and not (home / SCRATCH).exists() and not (ROOT / SCRATCH).exists()


@pytest.mark.slow
def test_a_prepared_folder_resumes_removing_only_its_own_leftovers(co3d, tmp_path):
    out = tmp_path / "prepared"
    first = _prepare(co3d, out, tmp_path)
    assert first.code == 0, first.stderr[-2000:]
    shards = sorted(out.rglob("*.safetensors"))
    assert len(shards) == 2 and not list((out / SCRATCH).iterdir())
    shards[0].unlink()
    leftover = out / SCRATCH / f".{shards[0].name}.tmp-00112233445566ff"  # what a killed run of prepare leaves
    leftover.write_bytes(b"half")
    notes = _foreign_folder(shards[1].parent)
    planted = out / SCRATCH / "keep.txt"  # not a name prepare makes: not removed either
    planted.write_text("mine")
    again = _prepare(co3d, out, tmp_path)
    assert again.code == 0, again.stderr[-2000:]
    assert "1 shards written, 1 already complete" in again.stdout
    assert shards[0].is_file() and not leftover.exists()
    assert notes.read_text() == "mine" and planted.read_text() == "mine"


@pytest.mark.slow
def test_prepare_refuses_a_scratch_folder_that_is_a_link(co3d, tmp_path):
    out = tmp_path / "prepared"
    assert _prepare(co3d, out, tmp_path).code == 0
    elsewhere = tmp_path / "elsewhere"
    victim = _foreign_folder(elsewhere).with_name(".a.safetensors.tmp-0123456789abcdef")
    victim.write_text("mine")
    (out / SCRATCH).rmdir()
    (out / SCRATCH).symlink_to(elsewhere)
    assert_refused(_prepare(co3d, out, tmp_path), f"--out: {out / SCRATCH} is not the folder prepare keeps")
    assert victim.read_text() == "mine" and (elsewhere / FOREIGN).read_text() == "mine"


@pytest.mark.slow
def test_prepare_out_that_is_a_file_or_cannot_be_made_is_named(co3d, tmp_path):
    file = tmp_path / "file"
    file.write_text("mine")
    assert_refused(_prepare(co3d, file, tmp_path), f"--out: {file} is a file, not a folder")
    assert_refused(_prepare(co3d, file / "sub", tmp_path), f"--out: cannot make the folder {file / 'sub'}")
    assert file.read_text() == "mine"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a mode-555 folder; the unmakeable case above covers it")
def test_prepare_into_a_read_only_folder_is_named(co3d, tmp_path):
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        assert_refused(_prepare(co3d, out, tmp_path), f"--out: cannot write {out / MANIFEST}")
    finally:
        out.chmod(stat.S_IRWXU)


@pytest.mark.slow
def test_export_views_refuses_a_link_planted_at_its_record(co3d, tmp_path):
    out = tmp_path / "views"
    out.mkdir()
    target = tmp_path / "target.json"
    (out / "objects.json").symlink_to(target)  # dangling: open(..., "w") would create the target
    outcome = run_command(["-m", "cdm.tools.export_views", "--out", str(out), "--set", "data.kind=co3d",
                           "--set", f"data.root={co3d}", "--set", "data.image_size=32"], tmp_path)
    assert_refused(outcome, f"--out: {out / 'objects.json'} is a symbolic link where this command writes a file")
    assert not os.path.lexists(target)


def test_a_crop_named_with_other_digits_is_named(tmp_path):
    views = tmp_path / "views"
    (views / "co3d" / "teddybear" / "s1").mkdir(parents=True)
    (views / "objects.json").write_text(json.dumps({"co3d/teddybear/s1": "teddybear"}))
    (views / "co3d" / "teddybear" / "s1" / "\u00b2.png").write_bytes(b"")
    outcome = run_command(["-m", "cdm.tools.estimate_depth", "--views", str(views), "--model", str(tmp_path / "m"),
                           "--out", str(tmp_path / "maps")], tmp_path)
    assert_refused(outcome, f"--views: {views / 'co3d' / 'teddybear' / 's1' / '².png'} is named with digits other")
    assert not (tmp_path / "maps").exists()


@pytest.fixture(scope="module")
def views_and_model(co3d, tmp_path_factory):
    pytest.importorskip("transformers", reason="the depth tool's optional extra: pip install -e '.[depth]'")
    from cdm.tools.export_views import main as export_main
    from tests.test_estimate_depth import tiny_dpt

    views = tmp_path_factory.mktemp("views")
    assert export_main(["--out", str(views), "--set", "data.kind=co3d", "--set", f"data.root={co3d}",
                        "--set", "data.image_size=32"]) == 0
    return views, tiny_dpt(tmp_path_factory.mktemp("dpt"))


@pytest.mark.slow
@pytest.mark.parametrize("command", [("-m", "cdm.tools.estimate_depth"), (str(ROOT / "sweeps" / "inputs.py"), "depth")])
def test_the_depth_tool_never_writes_through_a_planted_link(views_and_model, tmp_path, command):
    views, model = views_and_model
    out = tmp_path / "maps"
    out.mkdir()
    target = tmp_path / "outside" / "estimator.json"
    target.parent.mkdir()
    (out / "estimator.json").symlink_to(target)
    outcome = run_command([*command, "--views", str(views), "--model", model, "--out", str(out)], tmp_path)
    assert_refused(outcome, f"--out: {out / 'estimator.json'} is a symbolic link where this command writes a file")
    assert not os.path.lexists(target) and list(target.parent.iterdir()) == []


@pytest.mark.slow
def test_the_depth_tool_refuses_a_folder_link_below_out_and_an_out_that_is_a_file(views_and_model, tmp_path):
    views, model = views_and_model
    object_id = json.loads((views / "objects.json").read_text())
    first = sorted(object_id)[0]
    out = tmp_path / "maps"
    (out / first).parent.mkdir(parents=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / first).symlink_to(elsewhere, target_is_directory=True)
    command = ["-m", "cdm.tools.estimate_depth", "--views", str(views), "--model", model, "--out"]
    assert_refused(run_command([*command, str(out)], tmp_path), "--out: ", f"outside {out}")
    assert list(elsewhere.iterdir()) == []
    file = tmp_path / "file"
    file.write_text("mine")
    assert_refused(run_command([*command, str(file)], tmp_path), f"--out: {file} is a file, not a folder")
    assert file.read_text() == "mine"


@pytest.mark.parametrize("kind", ["config", pytest.param("spec", marks=pytest.mark.slow)])
def test_a_5001_digit_integer_in_a_yaml_file_is_named(tmp_path, kind):
    huge = "9" * 5001
    if kind == "config":
        path = tmp_path / "c.yaml"
        path.write_text(f"train:\n  steps: {huge}\n")
        command, said = ["-m", "cdm", "train", "--config", str(path)], f"config file: {path} "
    else:
        path = tmp_path / "s.yaml"
        path.write_text((ROOT / "sweeps" / "point_size.yaml").read_text() + f"\nextra: {huge}\n")
        command, said = [str(ROOT / "sweeps" / "run.py"), str(path), "--dry-run"], f"spec: {path} "
    line = assert_refused(run_command(command, tmp_path), said, "an integer of 5001 digits", "at most 1000")
    assert huge not in line
