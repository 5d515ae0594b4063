"""pyproject.toml's dependencies and constraints.txt agree: every dependency is pinned there, at a version its
bounds admit, and the packages whose minor releases break us (Ray's private API, MLflow's store) are held
below the next minor version."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

tomllib = pytest.importorskip("tomllib", reason="Python 3.11's TOML reader")

ROOT = Path(__file__).resolve().parents[1]
REQUIREMENTS = [Requirement(r) for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]]
PINS = {canonicalize_name(name): Version(version) for name, version in
        re.findall(r"^([A-Za-z0-9_.-]+)==(\S+)$", (ROOT / "constraints.txt").read_text(), re.M)}
HELD_AT_MINOR = {"ray": "2.60", "mlflow": "3.18"}
"""Tested minor version of each package bounded below the next one."""


@pytest.mark.parametrize("requirement", REQUIREMENTS, ids=str)
def test_each_dependency_is_pinned_in_constraints_within_its_bounds(requirement):
    name = canonicalize_name(requirement.name)
    assert name in PINS, f"constraints.txt pins no {requirement.name}: add the version the suite ran with"
    pin = PINS[name]
    assert requirement.specifier.contains(pin), f"constraints.txt's {name}=={pin} is outside {requirement}"


@pytest.mark.parametrize("requirement", REQUIREMENTS, ids=str)
def test_each_dependency_has_a_lower_bound_the_installed_version_meets(requirement):
    lows = [s.version for s in requirement.specifier if s.operator == ">="]
    assert lows, f"{requirement} has no lower bound"
    installed = Version(importlib.metadata.version(requirement.name))
    assert requirement.specifier.contains(installed), f"installed {requirement.name} {installed}: not {requirement}"


@pytest.mark.parametrize(("name", "minor"), sorted(HELD_AT_MINOR.items()))
def test_ray_and_mlflow_are_held_below_their_next_minor_version(name, minor):
    (requirement,) = [r for r in REQUIREMENTS if canonicalize_name(r.name) == name]
    major, low = map(int, minor.split("."))
    assert f"<{major}.{low + 1}" in {str(s) for s in requirement.specifier}, requirement
    assert not requirement.specifier.contains(f"{major}.{low + 1}.0")


def _imported_roots() -> set[str]:
    roots = set()
    for path in [*(ROOT / "cdm").rglob("*.py"), *(ROOT / "sweeps").rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                roots |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                roots.add(node.module.split(".")[0])
    return roots


IMPORT_NAMES = {"PIL": "pillow", "cv2": "opencv-python-headless", "yaml": "pyyaml", "grpc": "grpcio"}
OPTIONAL = {"transformers", "open_clip"}
"""Imported only by optional tools, which say how to install them: the depth tool (the ``depth`` extra) and
the OpenCLIP embeddings tool."""


def test_every_third_party_package_cdm_and_sweeps_import_is_declared():
    declared = {canonicalize_name(r.name) for r in REQUIREMENTS}
    third_party = {r for r in _imported_roots() if r not in sys.stdlib_module_names and r not in ("cdm", "sweeps")}
    missing = sorted(r for r in third_party - OPTIONAL if canonicalize_name(IMPORT_NAMES.get(r, r)) not in declared)
    assert missing == [], f"imported but not in pyproject.toml's dependencies: {missing}"
