"""``cdm-lab``: one command line whose commands are the project's commands, each the same command, one grammar.

The commands run as a user types them: the ``cdm-lab`` script that ``pip install -e .`` puts beside this
interpreter, or, where this checkout is not installed, ``python -m cdm.lab`` (what the script runs). The sweep
commands come from the entry points ``pip install -e .`` records, as an installed ``cdm-lab`` finds them.
Each command's help is compared with its old form's in this process (its file run as ``__main__`` by ``runpy``,
as tests/test_commands.py does). Every command's parser is walked for the grammar of :mod:`cdm.cli`, and
docs/cli.md is held to what ``python docs/cli.py`` writes from those parsers.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
from importlib.metadata import distribution
from pathlib import Path

import pytest

from cdm.__main__ import build_parser
from cdm.config import config_field_paths
from cdm.lab import COMMANDS, commands, main, parsers, version
from sweeps.lab import COMMANDS as SWEEP_COMMANDS
from tests.test_commands import _commands

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(sys.executable).parent / "cdm-lab"
CDM_LAB = [str(SCRIPT)] if SCRIPT.is_file() else [sys.executable, "-m", "cdm.lab"]


def _run(command: list[str], *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([*command, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


def _table(name: str) -> list[tuple[str, str]]:
    """The ``key = "value"`` lines of pyproject.toml's table ``name``."""
    text = (ROOT / "pyproject.toml").read_text().split(f"[{name}]\n", 1)[1].split("\n[", 1)[0]
    return re.findall(r"^([\w-]+) = \"(.+)\"$", text, re.M)


def test_the_project_installs_cdm_lab_as_its_one_script_and_the_sweeps_as_its_plug_in():
    assert _table("project.scripts") == [("cdm-lab", "cdm.lab:main")]
    assert _table('project.entry-points."cdm_lab.commands"') == [("sweeps", "sweeps.lab:COMMANDS")]
    assert _table('project.entry-points."cdm_lab.checkpoint_fetchers"') == [("mlflow", "sweeps.lab:fetch")]


def test_the_sweep_commands_are_listed_first_and_the_model_keeps_its_own():
    """Found through the installed entry points (``pip install -e .`` after a change to them), cdm importing
    nothing of sweeps/; a plug-in naming a model command would not change it."""
    assert list(commands()) == [*SWEEP_COMMANDS, *COMMANDS]
    assert commands()["run"] == SWEEP_COMMANDS["run"] and commands()["train"] == COMMANDS["train"]
    assert [c.old_form() for _, c in SWEEP_COMMANDS.values()][:2] == ["python sweeps/run.py", "python sweeps/report.py"]


def test_help_lists_every_command_and_imports_no_heavy_library():
    out = _run(CDM_LAB, "--help")
    assert out.returncode == 0, out.stderr
    listed = re.findall(r"^  ([a-z-]+) +(.+) \((python [^)]+)\)$", out.stdout, re.M)
    assert [(n, s, c) for n, s, c in listed] == [(n, c.summary, c.old_form()) for n, (_, c) in commands().items()]
    probe = "import sys; from cdm.lab import main\ntry: main(['--help'])\nexcept SystemExit: pass\n" \
            "print(sorted(m for m in ('torch', 'ray', 'mlflow', 'optuna', 'kornia') if m in sys.modules), " \
            "file=sys.stderr)"
    assert _run([sys.executable, "-c", probe]).stderr.strip() == "[]"


def test_bare_cdm_lab_lists_the_commands_and_an_unknown_one_exits_2_naming_the_choices():
    bare = _run(CDM_LAB)
    assert bare.returncode == 0 and bare.stderr == "" and bare.stdout == _run(CDM_LAB, "--help").stdout
    assert bare.stdout.startswith("usage: cdm-lab ") and all(f"\n  {name} " in bare.stdout for name in commands())
    out = _run(CDM_LAB, "tran")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.splitlines()[-1].startswith("cdm-lab: error: ")
    assert "invalid choice: 'tran' (choose from 'run', 'report'" in out.stderr


def test_version_names_the_release_and_this_checkouts_commit(capsys):
    assert main(["--version"]) == 0  # in this process: the commit is read with cdm.provenance, which imports torch
    out = capsys.readouterr()
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    version = re.search(r'^version = "(.+)"$', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    assert out.err == ""
    assert re.fullmatch(rf"cdm-lab {re.escape(version)} \(commit {head}(, modified)?\)\n", out.out), out.out


def test_version_outside_a_checkout_reads_the_installed_metadata(tmp_path):
    dist = distribution("cdm-lab")
    recorded = json.loads(dist.read_text("direct_url.json") or "{}").get("vcs_info", {}).get("commit_id", "unknown")
    assert version(tmp_path) == f"cdm-lab {dist.version} (commit {recorded})"


def test_every_command_of_the_project_is_a_cdm_lab_command():
    """A new subcommand of ``python -m cdm`` or a new command file of cdm/ or sweeps/ needs its cdm-lab command."""
    sub = {c.subcommand for _, c in commands().values() if c.subcommand is not None}
    (choices,) = [a.choices for a in build_parser()._actions if a.dest == "command"]
    assert sub == set(choices)
    files = {p for p in _commands() if p.startswith(("cdm/", "sweeps/"))} - {"cdm/lab.py"}
    assert {c.module.replace(".", "/") + ".py" for _, c in commands().values()} == files


@pytest.mark.parametrize("name", sorted(commands()))
def test_each_commands_help_is_its_old_forms_help(name, capsys, script_help):
    with pytest.raises(SystemExit) as exit_:
        main([name, "--help"])
    assert exit_.value.code == 0
    ours = capsys.readouterr().out
    assert ours.startswith("usage: ") and len(ours.splitlines()) > 3
    command = commands()[name][1]
    old = script_help(ROOT / (command.module.replace(".", "/") + ".py"), *filter(None, [command.subcommand]))
    assert ours == old  # the old form: the file or module run as __main__


@pytest.mark.slow  # four interpreters importing torch: 15 s on a busy 2-core machine
def test_a_command_prints_and_exits_as_its_old_form():
    fields = _run(CDM_LAB, "fields")
    assert fields.returncode == 0 and "priors.point_size" in fields.stdout
    old = _run([sys.executable, "-m", "cdm", "fields"])
    assert (fields.returncode, fields.stdout, fields.stderr) == (old.returncode, old.stdout, old.stderr)
    bad = ["sweeps/no_such_spec.yaml", "--smoke", "--dry-run"]
    ours, old = _run(CDM_LAB, "run", *bad), _run([sys.executable, "sweeps/run.py", *bad])
    assert ours.returncode == 2 and ours.stderr.startswith("error: ") and "no_such_spec.yaml" in ours.stderr
    assert (ours.returncode, ours.stdout, ours.stderr) == (old.returncode, old.stdout, old.stderr)


CONFIG_COMMANDS = {"run", "train", "train-prior", "evaluate", "reconstruct", "prepare", "check-data", "export-views",
                   "inputs prepare", "inputs all"}
"""The commands that build a config, and so take ``--set KEY=VALUE``; the others read no config."""
UNITS = ("degrees", "units", "pixels", "trials", "count", "crops", "integer")
"""One of these words in the help of every numeric flag: what its number counts or measures."""


def grammar_faults(name: str, parser: argparse.ArgumentParser) -> list[str]:
    """What in command ``name``'s parser breaks the shared grammar of cdm/cli.py, one line per fault."""
    faults = []
    if not parser.format_usage().startswith(f"usage: cdm-lab {name} "):
        faults.append(f"usage line {parser.format_usage().split(chr(10))[0]!r} does not name cdm-lab {name}")
    if not parser.description or "\n" in parser.description:
        faults.append("no one-line description")
    if not (parser.epilog or "").startswith(f"example:\n  cdm-lab {name} "):
        faults.append("no example")
    for action in parser._actions:
        flag = "/".join(action.option_strings) or action.dest
        if not action.help or action.help == argparse.SUPPRESS:
            faults.append(f"{flag}: no help")
        elif action.type in (int, float) and not any(unit in action.help for unit in UNITS):
            faults.append(f"{flag}: a number whose help names no unit ({action.help!r})")
        if "--out" in action.option_strings and (
                action.metavar != "DIR" or not action.help.startswith("folder")):
            faults.append(f"--out is not a folder: {action.metavar} {action.help!r}")
    has_set = any("--set" in a.option_strings for a in parser._actions)
    if has_set != (name in CONFIG_COMMANDS):
        faults.append("builds a config without --set" if not has_set else "--set on a command without a config")
    return faults


def test_every_command_keeps_the_grammar():
    walked = dict(parsers())
    assert set(commands()) | {"inputs prepare", "inputs depth", "inputs all"} == set(walked)
    faults = [f"cdm-lab {name}: {fault}" for name, parser in walked.items() for fault in grammar_faults(name, parser)]
    assert not faults, "\n".join(faults)
    takes = {}  # a flag is a switch everywhere or takes a value everywhere: one name, one meaning
    for parser in walked.values():
        for action in parser._actions:
            for flag in action.option_strings:
                takes.setdefault(flag, set()).add(action.nargs == 0)
    assert [flag for flag, kinds in takes.items() if len(kinds) > 1] == []
    assert takes["--resume"] == {True} and takes["--resume-from"] == {False}  # run's switch, train's folder


def test_every_config_field_a_help_or_example_names_is_one():
    texts = [a.help or "" for _, p in parsers() for a in p._actions] + [p.epilog or "" for _, p in parsers()]
    named = {key for text in texts for key in re.findall(r"\b([a-z_]+\.[a-z_0-9.]+)=", text)}
    assert {"data.kind", "priors.lambda_3d", "diffusion.sample_steps", "train.steps"} <= named
    assert named - set(config_field_paths()) == set()


def test_the_grammar_check_finds_each_fault():
    bad = argparse.ArgumentParser(prog="other.py", description="two\nlines")
    bad.add_argument("--seed", type=int)
    bad.add_argument("--out", help="a .ply file")
    bad.add_argument("--set", action="append", help="override")
    assert grammar_faults("fields", bad) == [
        "usage line 'usage: other.py [-h] [--seed SEED] [--out OUT] [--set SET]' does not name cdm-lab fields",
        "no one-line description", "no example", "--seed: no help", "--out is not a folder: None 'a .ply file'",
        "--set on a command without a config",
    ]


@pytest.mark.parametrize("path,args,name", [
    ("cdm/__main__.py", ["reconstruct"], "reconstruct"),
    ("sweeps/inputs.py", ["depth", "--no-such-flag"], "inputs depth"),
    ("sweeps/run.py", ["--no-such-flag"], "run"),
])
def test_an_argument_error_of_an_old_form_names_the_cdm_lab_command(path, args, name, monkeypatch, capsys):
    """``python -m cdm reconstruct``, ``python sweeps/inputs.py depth``, ``python sweeps/run.py``: run as users do."""
    import runpy

    monkeypatch.setattr(sys, "argv", [str(ROOT / path), *args])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(ROOT / path), run_name="__main__")
    err = capsys.readouterr().err.splitlines()
    assert exit_.value.code == 2 and err[0].startswith(f"usage: cdm-lab {name} ")
    assert err[-1].startswith(f"cdm-lab {name}: error: ")


_DATA = ["--root", "RAW", "--out", "prepared/"]
REMOVED = [
    ("train", ["--resume", "runs/quick/checkpoints/step_0000010"], []),
    ("reconstruct", ["--out", "chair.ply"], ["--checkpoint", "c/", "--image", "chair.png", "--ply", "chair.ply"]),
    ("prepare", ["--data-kind", "co3d"], _DATA),
    ("prepare", ["--image-size", "224"], _DATA),
    ("inputs prepare", ["--data-kind", "co3d"], _DATA),
    ("inputs prepare", ["--image-size", "224"], _DATA),
    ("inputs all", ["--data-kind", "co3d"], [*_DATA, "--model", "m/", "--inputs", "i/"]),
    ("inputs all", ["--image-size", "224"], [*_DATA, "--model", "m/", "--inputs", "i/"]),
    ("run", ["--storage", "results"], ["s.yaml"]),
    ("run", ["--rerun", "3f2a9c0d1e4b47a5"], ["s.yaml"]),
    ("run", ["--force"], ["s.yaml"]),
    ("run", ["--report", "point_size"], ["s.yaml"]),
    ("openclip-embeddings", ["--out", "image.npz"], ["--views", "v/", "--kind", "image", "--npz", "image.npz"]),
]
"""Each spelling 0.2.0 removed (CHANGELOG.md): the command, the removed flag as typed, and arguments that the
command takes without it."""


@pytest.mark.parametrize("name,removed,rest", REMOVED)
def test_a_removed_spelling_is_an_argument_error_and_the_changelog_names_it(name, removed, rest, capsys):
    """Not a prefix of another flag either (``--resume`` of ``--resume-from``): argparse's usage error, exit 2."""
    parser = dict(parsers())[name]
    parser.parse_args(rest)
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args([*rest, *removed])
    err = capsys.readouterr().err.splitlines()
    assert exit_.value.code == 2 and err[0].startswith(f"usage: cdm-lab {name} ")
    assert err[-1] == f"cdm-lab {name}: error: unrecognized arguments: {' '.join(removed)}"
    changes = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert f"`cdm-lab {name} {removed[0]}" in changes.split("\n### Removed\n", 1)[1].split("\n#")[0]


def test_docs_cli_md_is_what_the_parsers_write():
    spec = importlib.util.spec_from_file_location("docs_cli", ROOT / "docs" / "cli.py")
    page = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(page)
    written = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert written == page.render(), "docs/cli.md is stale: run python docs/cli.py"
    assert all(f"\n## cdm-lab {name}\n" in written for name in commands())
    assert "](docs/cli.md)" in (ROOT / "README.md").read_text(encoding="utf-8")
