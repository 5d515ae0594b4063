"""The walk of one hyperparameter (docs/ARCHITECTURE.md): ``priors.point_size`` followed for real, by tracing
every call that receives it, from ``sweeps/point_size.yaml`` through the plan stage and a trial's fit to the
footprint in ``cdm/render.py``. The files it passes must be the doc's list, at most 6 moves, none twice."""

from __future__ import annotations

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
OWN_RECORD = "cdm/config.py"
"""A method of the ``Config`` the value lives in (``replace``, ``flat``) keeps it in hand: no move (the doc)."""


def _holds(obj, depth: int = 0) -> bool:
    """Whether ``obj`` is the sentinel or holds it: in a dict, list or tuple, or a field of a project record."""
    if isinstance(obj, float):
        return obj == SENTINEL
    if depth > 8 or isinstance(obj, (str, bytes, int, type)):
        return False
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


def _doc_walk() -> list[str]:
    """The files of the doc's numbered list ``N. `A` → `B`: …``, checked to join up: [A₁, B₁, B₂, …]."""
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    section = text.split("## The walk of one hyperparameter", 1)[1].split("\n## ", 1)[0]
    moves = re.findall(r"^(\d+)\. `([^`]+)` → `([^`]+)`", section, flags=re.M)
    assert [int(n) for n, _, _ in moves] == list(range(1, len(moves) + 1)), "number the moves 1, 2, …"
    assert all(moves[i][2] == moves[i + 1][1] for i in range(len(moves) - 1)), "each move starts where the last ended"
    return [moves[0][1], *(to for _, _, to in moves)]


def _climbs(chain: list[str]) -> set[str]:
    """Files a chain enters twice: a function handing the value back into a file above it on the stack."""
    return {f for i, f in enumerate(chain) if f in chain[:i]}


def test_the_doc_reader_reads_the_moves_and_the_climb_finder_finds_one():
    assert _climbs(["sweeps/plan/trials.py", "cdm/config.py", "sweeps/plan/trials.py"]) == {"sweeps/plan/trials.py"}
    assert _climbs(["cdm/train.py", "cdm/objective.py", "cdm/render.py"]) == set()
    walk = _doc_walk()
    assert walk[0] == "sweeps/point_size.yaml" and walk[-1] == "cdm/render.py"


@pytest.mark.slow
def test_point_size_walks_from_the_yaml_to_the_footprint_as_the_doc_lists(tmp_path, monkeypatch):
    """The plan stage's entry expands a copy of point_size.yaml holding the sentinel; the trial side takes the
    config handed down in :class:`TrialSetup` and fits one step. Traced, the value must pass the doc's files
    in its order, ≤ 6 moves, no file twice; the trial side must not call back into a file of the plan's part."""
    monkeypatch.chdir(tmp_path)
    text = (ROOT / "sweeps" / "point_size.yaml").read_text()
    spec_file = tmp_path / "point_size.yaml"
    text = re.sub(r"priors\.point_size: \[[^\]]*\]", f"priors.point_size: [{SENTINEL}]", text)
    assert text.endswith("\n") and "\nprofiles:\n" in text  # the spec's own profiles come last: one step here
    spec_file.write_text(text + "  smoke:\n    budget: {steps: 1, eval_every: 1}\n")
    args = run._parser().parse_args([str(spec_file), "--smoke", "--storage", str(tmp_path / "results")])
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
    walk = ["sweeps/point_size.yaml", *plan_part, *trial_part]
    assert walk == _doc_walk()
    assert len(walk) - 1 <= 6 and len(set(walk)) == len(walk)
    # splat_points turns the radius in NDC into pixels (S/2 of them per NDC unit) for its footprint.
    assert SENTINEL * cell.config.priors.render_size / 2 in trial.footprints
    for calls in (planned.calls, trial.calls):
        assert not [(p, f, chain) for p, f, chain in calls if _climbs(chain)]
    back = {p for p, _, _ in trial.calls} & ({*plan_part} | {p for p, _, _ in planned.calls if "/plan/" in p})
    assert back == set(), f"the trial called back into the plan's files with the value: {back}"
