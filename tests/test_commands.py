"""What the commands print a newcomer: every ``--help`` opens with what the command does, and the
main job's dry-run prints no line over 200 characters, each profile's description in at most two.

Each command's file runs in this process (``runpy``) as its ``__main__``, which is what ``python FILE``
and ``python -m MODULE`` run, so the check costs no interpreter start per command.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sweeps import run
from sweeps.plan.profiles import load_profiles
from tests.input_fixtures import paper_inputs

ROOT = Path(__file__).resolve().parents[1]
MAX_LINE = 200  # characters of one printed line (issue 36)

# Each command and the words its --help opens with after the usage lines: the purpose, in a sentence.
PURPOSE = {
    "sweeps/run.py": "Run a sweep: train every trial of a spec on Ray",
    "sweeps/inputs.py": "Make a data set's inputs for the paper profile on Ray",
    "sweeps/rerun.py": "Re-run one finished trial of a sweep from its MLflow record",
    "sweeps/report.py": "Rebuild a finished sweep's comparison straight from MLflow",
    "sweeps/register.py": "Register a finished sweep's best cell's model in MLflow's model registry",
    "cdm/lab.py": "One command line for CDM Lab",
    "cdm/__main__.py": "Train, evaluate and use a CDM model without a sweep",
    "cdm/tools/export_views.py": "Write the images a config's data set shows the model",
    "cdm/tools/estimate_depth.py": "Estimate the paper's 2D depth prior on exported views",
    "cdm/tools/openclip_embeddings.py": "Write the per-object embeddings of supplementary Table 7",
    "benchmarks/run.py": "Run the benchmarks and print one Markdown table",
    "benchmarks/denoiser_step.py": "Time one training step of each denoiser on CPU",
    "benchmarks/sweep_cpu.py": "Measure the CPU a training step takes inside a real sweep",
    "benchmarks/cpu_modes.py": "Pinned CPU kernels against the default",
    "benchmarks/gpu_check.py": "One device script: every figure a cluster user needs for the paper profile",
    "benchmarks/step_ops.py": "Ops dispatched per pvcnn2 training step, and per point operation",
    "benchmarks/model_logging.py": "What a trial pays per checkpoint to log its weights",
    "benchmarks/checkpoint_load.py": "Loading a training checkpoint: 0.1.0's",
    "benchmarks/lean_step.py": "The local training step, this tree ÷ the tree at a base revision, side by side",
    "docs/screenshots.py": "Take the README's pictures of a finished sweep",
    "docs/cli.py": "Write docs/cli.md from the parsers of every cdm-lab command",
    "docs/architecture.py": "Draw the import picture of docs/ARCHITECTURE.md from the code",
}


def _commands() -> set[str]:
    """Every file a user runs: ``if __name__ == "__main__"`` in the project's folders, and ``cdm/__main__.py``."""
    found = {"cdm/__main__.py"}
    for folder in ("cdm", "sweeps", "benchmarks", "docs"):
        for path in (ROOT / folder).rglob("*.py"):
            if re.search(r"^if __name__ == .__main__.:", path.read_text(), re.M):
                found.add(str(path.relative_to(ROOT)))
    return found


def test_every_command_has_a_stated_purpose():
    assert _commands() == set(PURPOSE), "add each new command, with the words its --help opens with, to PURPOSE"


@pytest.mark.parametrize("command", sorted(PURPOSE))
def test_help_opens_with_what_the_command_does(command, script_help):
    text = script_help(ROOT / command)
    # argparse prints the usage lines, a blank line, then the description.
    description = text.split("\n\n", 2)[1]
    assert " ".join(description.split()).startswith(PURPOSE[command]), description
    assert "400 lines" not in text


@pytest.mark.parametrize("profile", sorted(load_profiles()))
def test_the_main_job_dry_run_prints_short_lines_and_a_two_line_profile(profile, tmp_path, monkeypatch, capsys):
    """The main job (``sweeps/point_size.yaml``) in every profile, its cost estimate included."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CDM_INPUTS", str(paper_inputs(tmp_path / "inputs")))
    extra = [] if profile == "smoke" else ["--no-estimate"]  # the estimate's calibration trains a few steps
    assert run.main([str(ROOT / "sweeps" / "point_size.yaml"), "--dry-run", "--profile", profile, *extra]) == 0
    lines = capsys.readouterr().out.splitlines()
    long = [f"{len(line)}: {line[:80]}…" for line in lines if len(line) > MAX_LINE]
    assert not long, f"lines over {MAX_LINE} characters:\n" + "\n".join(long)
    assert extra or any(line.startswith("estimate: ") for line in lines)
    start = next(i for i, line in enumerate(lines) if line.startswith(f"profile {profile}: "))
    continued = 0
    while lines[start + 1 + continued].startswith("  "):
        continued += 1
    assert 1 + continued <= 2, "\n".join(lines[start: start + 2 + continued])
