"""The walk of one hyperparameter (docs/ARCHITECTURE.md): ``priors.point_size`` followed for real, by tracing
every call that receives it, from ``sweeps/point_size.yaml`` through the read of that file, the plan stage and
a trial's fit to the footprint in ``cdm/render.py``. The value is received as the spec file's path, its line
of text, or a record holding the number. It must reach the footprint, enter no file twice on one call chain,
and pass every function the doc's walk names on the parts traced here (its steps' code is checked by
tests/test_architecture.py)."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import re
import sys
import warnings
from pathlib import Path

import pytest
from pydantic import BaseModel

from sweeps import run
from sweeps.execute.trial import TrialSetup, fit_trial, trial_job
from sweeps.plan.request import plan_request

ROOT = Path(__file__).resolve().parents[1]
_SPEC = importlib.util.spec_from_file_location("docs_architecture", ROOT / "docs" / "architecture.py")
arch = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(arch)
SENTINEL = 0.0371
"""The point size planted in the YAML: no default or profile holds it, so any float equal to it is the value."""
LINE = f"priors.point_size: [{SENTINEL}]"
"""The spec's line that holds it: text (or bytes) holding this line is the value still being read."""
SPEC_PATHS: set[str] = set()
"""The planted spec file's path, as a string: a call handed the path is handed the value in its file."""
OWN_RECORD = "cdm/config.py"
"""A method of the ``Config`` the value lives in (``replace``, ``flat``) keeps it in hand: no move (the doc)."""


def _holds(obj, depth: int = 0) -> bool:
    """Whether ``obj`` is the sentinel or holds it: in a dict, list or tuple, or a field of a project record."""
    if isinstance(obj, float):
        return obj == SENTINEL
    if isinstance(obj, (str, Path)):
        return str(obj) in SPEC_PATHS or LINE in str(obj)
    if isinstance(obj, (bytes, bytearray)):
        return LINE.encode() in obj
    if depth > 8 or isinstance(obj, (int, type)):
        return False
    if isinstance(obj, argparse.Namespace):  # the command line's arguments: the spec's path among them
        return any(_holds(v, depth + 1) for v in vars(obj).values())
    if isinstance(obj, dict):
        return any(_holds(v, depth + 1) for v in list(obj.values())[:64])
    if isinstance(obj, (list, tuple)):
        return any(_holds(v, depth + 1) for v in obj[:64])
    if type(obj).__module__.split(".")[0] not in ("cdm", "sweeps"):
        return False
    if dataclasses.is_dataclass(obj):
        return any(_holds(getattr(obj, f.name), depth + 1) for f in dataclasses.fields(obj))
    if isinstance(obj, BaseModel):
        return any(_holds(v, depth + 1) for v in obj.__dict__.values())
    return False


def _project_file(frame) -> str | None:
    path = Path(frame.f_code.co_filename)
    if path.is_relative_to(ROOT) and path.relative_to(ROOT).parts[0] in ("cdm", "sweeps"):
        return path.relative_to(ROOT).as_posix()
    return None


def _receives(frame) -> bool:
    """Whether the function of ``frame`` was handed the value: an argument holds it, ``self`` included."""
    code = frame.f_code
    count = code.co_argcount + code.co_kwonlyargcount + bool(code.co_flags & 4) + bool(code.co_flags & 8)
    return any(_holds(frame.f_locals[n]) for n in code.co_varnames[:count] if n in frame.f_locals)


def _in_own_record(frame) -> bool:
    """Whether ``frame`` runs inside a method of the value's own record (``Config.replace`` and what it calls)."""
    while frame is not None:
        if _project_file(frame) == OWN_RECORD and frame.f_code.co_varnames[:1] == ("self",):
            return True
        frame = frame.f_back
    return False


class Walk:
    """Every call of a project function that receives the value, with the chain of project files that
    handed it down: the files of the frames on the stack that received it, outermost first, each once in a row."""

    def __init__(self):
        self.calls: list[tuple[str, str, list[str]]] = []
        self.seen: set[tuple[str, str]] = set()
        """Every project function called, value or not: ``(file, function name)``."""
        self.footprints: list[float] = []
        """The radius (pixels) of every ``cdm/render.py`` footprint made: the value's use, derived from it."""

    def _profile(self, frame, event, arg):
        if event != "call" or (path := _project_file(frame)) is None:
            return
        self.seen.add((path, frame.f_code.co_name))
        if (path, frame.f_code.co_name) == ("cdm/render.py", "_footprint"):
            self.footprints.append(frame.f_locals["radius_px"])
        if not _receives(frame) or _in_own_record(frame):
            return
        chain, outer = [path], frame.f_back
        while outer is not None:
            if (outer_path := _project_file(outer)) is not None and _receives(outer) and outer_path != chain[-1]:
                chain.append(outer_path)
            outer = outer.f_back
        self.calls.append((path, frame.f_code.co_name, chain[::-1]))

    def __enter__(self):
        sys.setprofile(self._profile)
        return self

    def __exit__(self, *exc):
        sys.setprofile(None)

    def chain_to(self, path: str, function: str) -> list[str]:
        return next(chain for p, f, chain in self.calls if (p, f) == (path, function))


def _doc_functions(start: str) -> set[tuple[str, str]]:
    """``(file, function name)`` of every function the doc's walk reaches from ``start`` (``file:function``), and
    ``("", name)`` of each helper it names on the way; a step into a callback the traced fit leaves out (the
    MLflow ``TrialRun``) is not followed."""
    steps = arch.walk_steps((ROOT / "docs" / "ARCHITECTURE.md").read_text())
    reached, out = {start}, set()
    for step in steps:
        if f"{step.caller_file}:{step.caller}" in reached and not step.callee.startswith("TrialRun."):
            reached.add(f"{step.callee_file}:{step.callee}")
            out |= {(step.callee_file, step.callee.rpartition(".")[2])}
            out |= {("", helper.rpartition(".")[2]) for helper in step.through}
    return out


def _not_called(wanted: set[tuple[str, str]], seen: set[tuple[str, str]]) -> set[tuple[str, str]]:
    """Functions of ``wanted`` that ``seen`` lacks; a helper's empty file matches any file."""
    names = {name for _, name in seen}
    return {(f, name) for f, name in wanted if ((f, name) not in seen if f else name not in names)}


def _climbs(chain: list[str]) -> set[str]:
    """Files a chain enters twice: a function handing the value back into a file above it on the stack."""
    return {f for i, f in enumerate(chain) if f in chain[:i]}


def test_the_climb_finder_finds_one_and_the_doc_reader_follows_the_walk_from_a_function():
    assert _climbs(["sweeps/plan/trials.py", "cdm/config.py", "sweeps/plan/trials.py"]) == {"sweeps/plan/trials.py"}
    assert _climbs(["cdm/train.py", "cdm/objective.py", "cdm/render.py"]) == set()
    assert ("cdm/render.py", "splat_points") in _doc_functions("sweeps/execute/trial.py:fit_trial")
    assert ("cdm/render.py", "splat_points") not in _doc_functions("sweeps/plan/request.py:plan_request")
    assert _not_called({("a.py", "f"), ("", "_g"), ("b.py", "h")}, {("a.py", "f"), ("c.py", "_g")}) == {("b.py", "h")}
    assert _holds(Path("x.yaml")) is False and _holds(f"a: 1\n{LINE}\n") and _holds(LINE.encode())


@pytest.mark.slow
def test_point_size_walks_from_the_yaml_to_the_footprint_as_the_doc_lists(tmp_path, monkeypatch):
    """The plan stage's entry reads and expands a copy of point_size.yaml holding the sentinel; the trial side
    takes the config handed down in :class:`TrialSetup` and fits one step. Traced, the value must reach the
    footprint, every function the doc's walk names on these parts must run, no call chain may enter a file
    twice, and the trial side must not call back into a file of the plan's part."""
    monkeypatch.chdir(tmp_path)
    text = (ROOT / "sweeps" / "point_size.yaml").read_text()
    spec_file = tmp_path / "point_size.yaml"
    text = re.sub(r"priors\.point_size: \[[^\]]*\]", LINE, text)
    assert text.endswith("\n") and "\nprofiles:\n" in text  # the spec's own profiles come last: one step here
    spec_file.write_text(text + "  smoke:\n    budget: {steps: 1, eval_every: 1}\n")
    monkeypatch.setattr(sys.modules[__name__], "SPEC_PATHS", {str(spec_file)})
    args = run.build_parser().parse_args([str(spec_file), "--smoke", "--out", str(tmp_path / "results")])
    with Walk() as planned:
        request = plan_request(args)
    (cell,) = request.plan.cells
    assert cell.config.priors.point_size == SENTINEL
    setup = TrialSetup(request.plan, {c.label: c for c in request.plan.cells}, request.sweep_dir,
                       "sqlite:///unused.db", "0", "parent", {}, None, 0)
    with Walk() as trial, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Ray's "report outside a Tuner": this trial runs without Ray
        fit_trial(trial_job(setup, {"cell": cell.label}, "walk", "node", tmp_path / "trial"), 0, lambda c: [])
    plan_part = planned.chain_to("cdm/config.py", "load_config")
    trial_part = trial.chain_to("cdm/render.py", "splat_points")
    assert plan_part[0] == "sweeps/plan/request.py" and trial_part[0] == "sweeps/execute/trial.py"
    # Every function the doc's walk names from the plan's entry and from the trial's fit on was called.
    assert _not_called(_doc_functions("sweeps/plan/request.py:plan_request"), planned.seen) == set()
    assert _not_called(_doc_functions("sweeps/execute/trial.py:fit_trial"), trial.seen) == set()
    # splat_points turns the radius in NDC into pixels (S/2 of them per NDC unit) for its footprint.
    assert SENTINEL * cell.config.priors.render_size / 2 in trial.footprints
    for calls in (planned.calls, trial.calls):
        assert not [(p, f, chain) for p, f, chain in calls if _climbs(chain)]
    back = {p for p, _, _ in trial.calls} & ({*plan_part} | {p for p, _, _ in planned.calls if "/plan/" in p})
    assert back == set(), f"the trial called back into the plan's files with the value: {back}"
