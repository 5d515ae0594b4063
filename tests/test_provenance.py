"""cdm/provenance.py: the machine record names this CPU, the kernels it picks and every installed package."""

from __future__ import annotations

import re
from importlib.metadata import version
from pathlib import Path

import pytest
import torch

from cdm.digest import json_digest
from cdm.provenance import ISA_FLAGS, KERNEL_PINS, MACHINE_KEYS, installed_packages, machine_record

CPUINFO = Path("/proc/cpuinfo")


@pytest.fixture
def unpinned(monkeypatch):
    for name in KERNEL_PINS:
        monkeypatch.delenv(name, raising=False)


@pytest.mark.skipif(not CPUINFO.exists(), reason="reads /proc/cpuinfo (Linux)")
def test_the_record_names_this_cpu_its_isa_and_atens_capability(unpinned):
    record = machine_record()
    assert tuple(record) == MACHINE_KEYS
    info = CPUINFO.read_text()
    assert f"model name\t: {record['cpu_model']}\n" in info and record["cpu_model"]
    flags = set(re.search(r"^flags\s*:(.*)$", info, re.MULTILINE).group(1).split())
    assert record["cpu_isa"].split() == [f for f in ISA_FLAGS if f in flags]
    assert record["cpu_capability"] == torch.backends.cpu.get_cpu_capability()


def test_the_math_libraries_line_is_short_and_quotes_torchs_build(unpinned):
    line, shown = machine_record()["math_libraries"], torch.__config__.show()
    blas = re.search(r"BLAS_INFO=(\w+)", shown).group(1)
    assert line.startswith(f"BLAS {blas}") and len(line) < 80 and "\n" not in line
    for number in re.findall(r"\d[\d.]+\d|\b[0-9a-f]{7}\b", line):  # versions, builds and hashes are torch's
        assert number in shown, number
    if "MKL-DNN v" in shown:
        assert re.search(r"oneDNN \d+\.\d+\.\d+ \([0-9a-f]{7}\)", line)


def test_kernel_pins_are_named_as_set(unpinned, monkeypatch):
    assert machine_record()["kernel_pins"] == "none"
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    assert machine_record()["kernel_pins"] == "MKL_CBWR=COMPATIBLE ATEN_CPU_CAPABILITY=avx2"


def _fake_distribution(folder: Path, name: str, ver: str) -> None:
    info = folder / f"{name}-{ver}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {ver}\n")


def test_every_package_is_listed_once_whatever_the_process_imported():
    before = installed_packages()
    names = [line.split("==")[0] for line in before]
    assert names == sorted(set(names)) and len(names) > 50
    assert f"torch=={version('torch')}" in before and f"numpy=={version('numpy')}" in before
    assert machine_record()["packages_digest"] == json_digest(before)
    import ray  # noqa: F401 — puts its private copies of packages (ray/thirdparty_files) on sys.path

    assert installed_packages() == before


def test_the_first_of_a_name_counts_and_any_change_changes_the_digest(tmp_path):
    _fake_distribution(tmp_path / "a", "Fake_Pkg", "1.0")
    _fake_distribution(tmp_path / "b", "fake.pkg", "2.0")  # the same name, later on the path: shadowed
    _fake_distribution(tmp_path / "b", "other", "3.1")
    listed = installed_packages([str(tmp_path / "a"), str(tmp_path / "b")])
    assert listed == ["fake-pkg==1.0", "other==3.1"]
    assert json_digest(listed) != json_digest(installed_packages([str(tmp_path / "b"), str(tmp_path / "a")]))
