"""Ray's private API stays in ``sweeps/ray_internals.py`` and fails loudly on a Ray it was not read against."""

from __future__ import annotations

import importlib
import logging
import re
from pathlib import Path

import pytest
import ray

from sweeps import ray_internals
from sweeps.ray_internals import PRIVATE_NAMES, TESTED_RAY

ROOT = Path(__file__).resolve().parents[1]
RECHECK = (f"sweeps/ray_internals.py was read against Ray {TESTED_RAY}; with Ray {ray.__version__} re-read each "
           "function's source file named in its docstring, run tests/test_ray_address.py, tests/test_cluster.py, "
           "tests/test_progress.py and the local-cluster tests, then raise TESTED_RAY and pyproject.toml's ray bound")


def test_the_installed_ray_is_the_minor_version_the_private_calls_were_read_against():
    assert ".".join(ray.__version__.split(".")[:2]) == TESTED_RAY, RECHECK


def test_pyproject_bounds_ray_below_the_next_minor_version():
    major, minor = map(int, TESTED_RAY.split("."))
    text = (ROOT / "pyproject.toml").read_text()
    assert re.search(rf'"ray\[[^\]]*\]>={major}\.{minor}(\.\d+)?,<{major}\.{minor + 1}"', text), RECHECK


@pytest.mark.parametrize(("module", "name"), PRIVATE_NAMES)
def test_each_private_name_still_exists(module, name):
    assert hasattr(importlib.import_module(module), name), f"{module}.{name} is gone. {RECHECK}"


def test_the_token_note_logger_is_the_one_ray_logs_on():
    assert importlib.import_module(ray_internals.TOKEN_NOTE_LOGGER).logger is logging.getLogger(
        ray_internals.TOKEN_NOTE_LOGGER)


def test_the_switches_set_what_ray_reads_and_put_it_back():
    import ray._private.ray_constants as constants
    import ray._private.ray_logging as ray_logging

    flag, dedup = constants.ENABLE_RAY_CLUSTER, ray_logging.RAY_DEDUP_LOGS
    try:
        ray_internals.set_loopback_flag(not flag)
        assert ray_internals.loopback_flag() is (not flag) and constants.ENABLE_RAY_CLUSTER is (not flag)
        ray_internals.set_log_dedup(False)
        assert ray_logging.RAY_DEDUP_LOGS is False
        ray_internals.set_log_dedup(True)
        assert ray_logging.RAY_DEDUP_LOGS is True
    finally:
        ray_internals.set_loopback_flag(flag)
        ray_logging.RAY_DEDUP_LOGS = dedup
    assert constants.ENABLE_RAY_CLUSTER is flag


def test_a_loopback_address_is_joined_as_given_when_ray_keeps_loopback():
    flag = ray_internals.loopback_flag()
    try:
        ray_internals.set_loopback_flag(False)
        assert ray_internals.canonical_address("127.0.0.1:6379") == "127.0.0.1:6379"
        assert ray_internals.canonical_address("10.0.0.10:6379") == "10.0.0.10:6379"
    finally:
        ray_internals.set_loopback_flag(flag)


def test_ray_private_appears_in_one_module_of_cdm_and_sweeps_only():
    # As `grep -rn "ray._private" cdm sweeps` finds it: "ray/_private/…" in a comment counts too.
    found = sorted(str(p.relative_to(ROOT)) for package in ("cdm", "sweeps") for p in (ROOT / package).rglob("*.py")
                   if re.search(r"ray._private", p.read_text()))
    assert found == ["sweeps/ray_internals.py"]
