"""``cdm-lab``: one command line whose commands are the project's commands, each the same command.

The commands run as a user types them: the ``cdm-lab`` script that ``pip install -e .`` puts beside this
interpreter, or, where this checkout is not installed, ``python -m sweeps.cdm_lab`` (what the script runs).
Each command's help is compared with its old form's in this process (its file run as ``__main__`` by ``runpy``,
as tests/test_commands.py does).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cdm.__main__ import build_parser
from sweeps.cdm_lab import COMMANDS, main
from tests.test_commands import _commands

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(sys.executable).parent / "cdm-lab"
CDM_LAB = [str(SCRIPT)] if SCRIPT.is_file() else [sys.executable, "-m", "sweeps.cdm_lab"]


def _run(command: list[str], *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([*command, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


def test_the_project_installs_cdm_lab_as_its_one_script():
    scripts = (ROOT / "pyproject.toml").read_text().split("[project.scripts]\n", 1)[1].split("\n[", 1)[0]
    assert re.findall(r"^([\w-]+) = \"(.+)\"$", scripts, re.M) == [("cdm-lab", "sweeps.cdm_lab:main")]


def test_help_lists_every_command_and_imports_no_heavy_library():
    out = _run(CDM_LAB, "--help")
    assert out.returncode == 0, out.stderr
    listed = re.findall(r"^  ([a-z-]+) +(.+) \((python [^)]+)\)$", out.stdout, re.M)
    assert [(n, s, c) for n, s, c in listed] == [(n, c.summary, c.old_form()) for n, (_, c) in COMMANDS.items()]
    probe = "import sys; from sweeps.cdm_lab import main\ntry: main(['--help'])\nexcept SystemExit: pass\n" \
            "print(sorted(m for m in ('torch', 'ray', 'mlflow', 'optuna') if m in sys.modules), file=sys.stderr)"
    assert _run([sys.executable, "-c", probe]).stderr.strip() == "[]"


def test_no_command_or_an_unknown_one_exits_2_naming_the_choices():
    for args in ([], ["tran"]):
        out = _run(CDM_LAB, *args)
        assert out.returncode == 2 and out.stdout == ""
        assert out.stderr.splitlines()[-1].startswith("cdm-lab: error: ")
    assert "invalid choice: 'tran' (choose from 'run', 'report'" in out.stderr


def test_every_command_of_the_project_is_a_cdm_lab_command():
    """A new subcommand of ``python -m cdm`` or a new command file of cdm/ or sweeps/ needs its cdm-lab command."""
    sub = {c.subcommand for _, c in COMMANDS.values() if c.subcommand is not None}
    (choices,) = [a.choices for a in build_parser()._actions if a.dest == "command"]
    assert sub == set(choices)
    files = {p for p in _commands() if p.startswith(("cdm/", "sweeps/"))} - {"sweeps/cdm_lab.py"}
    assert {c.module.replace(".", "/") + ".py" for _, c in COMMANDS.values()} == files


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_each_commands_help_is_its_old_forms_help(name, capsys, script_help):
    with pytest.raises(SystemExit) as exit_:
        main([name, "--help"])
    assert exit_.value.code == 0
    ours = capsys.readouterr().out
    assert ours.startswith("usage: ") and len(ours.splitlines()) > 3
    command = COMMANDS[name][1]
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
