"""The walk of one hyperparameter (docs/ARCHITECTURE.md): ``priors.point_size`` followed for real, by tracing
every call that receives it, from ``sweeps/point_size.yaml`` through the read of that file, the plan stage and
a trial's fit to the footprint in ``cdm/render.py``. The value is received as the spec file's path, its line
of text, or a record holding the number. The moves and the files they pass, counted as a newcomer reading the
code counts them, must be the doc's list and its figures, no file entered twice on one call chain."""

from __future__ import annotations

import argparse
import dataclasses
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
        self.footprints: list[float] = []
        """The radius (pixels) of every ``cdm/render.py`` footprint made: the value's use, derived from it."""

    def _profile(self, frame, event, arg):
        if event != "call" or (path := _project_file(frame)) is None:
            return
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


def _doc_walk() -> tuple[list[tuple[str, str]], int, int]:
    """The doc's numbered moves ``N. `A` → `B`: …`` (each starting in a file an earlier move reached, the
    first in the spec), and its figures: files passed and moves."""
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    section = text.split("## The walk of one hyperparameter", 1)[1].split("\n## ", 1)[0]
    moves = re.findall(r"^(\d+)\. `([^`]+)` → `([^`]+)`", section, flags=re.M)
    assert [int(n) for n, _, _ in moves] == list(range(1, len(moves) + 1)), "number the moves 1, 2, …"
    reached = [moves[0][1]]
    for _, start, end in moves:
        assert start in reached, f"move from {start}, which no earlier move reached"
        reached.append(end)
    figures = re.search(r"passes \*\*(\d+) files\*\* in \*\*(\d+) moves\*\*", section)
    assert figures, "say the walk's figures: passes **N files** in **M moves**"
    return [(a, b) for _, a, b in moves], int(figures[1]), int(figures[2])


def _moves(chain: list[str]) -> list[tuple[str, str]]:
    return list(zip(chain, chain[1:]))


def _climbs(chain: list[str]) -> set[str]:
    """Files a chain enters twice: a function handing the value back into a file above it on the stack."""
    return {f for i, f in enumerate(chain) if f in chain[:i]}


def test_the_doc_reader_reads_the_moves_and_the_climb_finder_finds_one():
    assert _climbs(["sweeps/plan/trials.py", "cdm/config.py", "sweeps/plan/trials.py"]) == {"sweeps/plan/trials.py"}
    assert _climbs(["cdm/train.py", "cdm/objective.py", "cdm/render.py"]) == set()
    moves, files, count = _doc_walk()
    assert moves[0][0] == "sweeps/point_size.yaml" and moves[-1][1] == "cdm/render.py"
    assert count == len(moves) and files == len({f for move in moves for f in move})
    assert _holds(Path("x.yaml")) is False and _holds(f"a: 1\n{LINE}\n") and _holds(LINE.encode())


@pytest.mark.slow
def test_point_size_walks_from_the_yaml_to_the_footprint_as_the_doc_lists(tmp_path, monkeypatch):
    """The plan stage's entry reads and expands a copy of point_size.yaml holding the sentinel; the trial side
    takes the config handed down in :class:`TrialSetup` and fits one step. Traced, the value must make the
    doc's moves, in its order, and pass as many files as the doc says; no call chain may enter a file twice;
    the trial side must not call back into a file of the plan's part."""
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
    read = [planned.chain_to("cdm/io/files.py", "read_bounded"), planned.chain_to("cdm/io/json.py", "bracket_depth")]
    plan_part = planned.chain_to("cdm/config.py", "load_config")
    trial_part = trial.chain_to("cdm/render.py", "splat_points")
    # The spec hands its path to the entry; the plan's hand-down to the trial is one move (the doc).
    traced = [("sweeps/point_size.yaml", plan_part[0])]
    for move in [m for chain in (*read, plan_part) for m in _moves(chain)] + [(plan_part[-1], trial_part[0])]:
        if move not in traced:
            traced.append(move)
    traced += _moves(trial_part)
    moves, files, count = _doc_walk()
    assert traced == moves
    assert (len({f for move in traced for f in move}), len(traced)) == (files, count)
    # splat_points turns the radius in NDC into pixels (S/2 of them per NDC unit) for its footprint.
    assert SENTINEL * cell.config.priors.render_size / 2 in trial.footprints
    for calls in (planned.calls, trial.calls):
        assert not [(p, f, chain) for p, f, chain in calls if _climbs(chain)]
    back = {p for p, _, _ in trial.calls} & ({*plan_part} | {p for p, _, _ in planned.calls if "/plan/" in p})
    assert back == set(), f"the trial called back into the plan's files with the value: {back}"
