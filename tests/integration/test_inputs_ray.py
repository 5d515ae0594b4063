"""``python sweeps/inputs.py``: the paper's inputs made as Ray tasks on a loopback cluster of two nodes
(issue 44): the same shards as ``python -m cdm prepare`` byte for byte, a killed run resumed without
rewriting a finished shard, a bad object failing alone, and the ``all`` command's steps."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sweeps import inputs
from tests.datasets_fixtures import make_co3d
from tests.integration.local_ray import TwoNodes, two_node_cluster

pytestmark = [pytest.mark.ray, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
SIZE = ["--set", "data.image_size=32"]


@pytest.fixture(scope="module")
def two_nodes() -> Iterator[TwoNodes]:
    with two_node_cluster() as cluster:
        yield cluster


@pytest.fixture(scope="module")
def co3d(tmp_path_factory) -> Path:
    """Co3D's layout with 2 × 40 sequences of large frames (×6: 576×432), so preparing one takes long
    enough for a kill to land part way."""
    tree = make_co3d(tmp_path_factory.mktemp("co3d"), frames=3, upscale=6, splits={"train": 30, "val": 10, "test": 1})
    (tree.root / "held_out.txt").write_text(tree.sequences["hydrant"]["val"][0])
    return tree.root


@pytest.fixture(scope="module")
def one_process(co3d, tmp_path_factory) -> Path:
    """The shards ``python -m cdm prepare`` writes in one process: the reference."""
    out = tmp_path_factory.mktemp("one") / "prepared"
    done = subprocess.run([sys.executable, "-m", "cdm", "prepare", "--set", "data.kind=co3d", "--root", str(co3d),
                           "--out", str(out), *SIZE], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return out


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _driver(args: list[str], address: str) -> subprocess.Popen:
    """``python sweeps/inputs.py ARGS`` joining the two-node cluster from another process."""
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "sweeps/inputs.py", *args, "--address", address], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def test_shards_made_on_two_nodes_equal_the_one_process_run_byte_for_byte(
    two_nodes, co3d, one_process, tmp_path, capsys
):
    out = tmp_path / "prepared"
    assert inputs.main(["prepare", "--set", "data.kind=co3d", "--root", str(co3d), "--out", str(out), *SIZE]) == 0
    assert "prepared" in capsys.readouterr().out
    ours, reference = _files(out), _files(one_process)
    assert len([k for k in reference if k.endswith(".safetensors")]) == 80
    assert ours.keys() == reference.keys() and all(ours[k] == reference[k] for k in ours)


def test_a_killed_prepare_resumes_without_rewriting_a_finished_shard(two_nodes, co3d, one_process, tmp_path):
    out = tmp_path / "prepared"
    args = ["prepare", "--set", "data.kind=co3d", "--root", str(co3d), "--out", str(out), *SIZE]
    driver = _driver(args, two_nodes.address)
    deadline = time.monotonic() + 120
    while not any(out.rglob("*.safetensors")) and driver.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.killpg(driver.pid, signal.SIGKILL)
    driver.wait(timeout=30)
    # The driver's tasks end with it; wait until no shard appears for 3 s.
    count, still = -1, 0.0
    while still < 3.0:
        time.sleep(0.5)
        now = sum(1 for _ in out.rglob("*.safetensors"))
        still, count = (still + 0.5, now) if now == count else (0.0, now)
    assert 0 < count < 80, f"the kill landed after {count} of 80 shards"
    finished = {p: p.stat().st_mtime_ns for p in out.rglob("*.safetensors")}

    rerun = _driver(args, two_nodes.address)
    stdout, stderr = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, stderr
    assert f"{80 - count} shards written, {count} already complete" in stdout
    assert all(p.stat().st_mtime_ns == t for p, t in finished.items())
    assert not [p for p in out.rglob("*") if ".tmp-" in p.name]
    assert _files(out) == _files(one_process)
    assert "Traceback" not in stdout + stderr


def test_a_bad_object_fails_alone_and_is_named(two_nodes, co3d, tmp_path):
    root = tmp_path / "co3d"
    shutil.copytree(co3d, root)
    sequence = (root / "held_out.txt").read_text()
    bad = sorted((root / "hydrant" / sequence / "images").glob("*.jpg"))[0]
    bad.write_bytes(b"not a jpeg")
    out = tmp_path / "prepared"
    driver = _driver(
        ["prepare", "--set", "data.kind=co3d", "--root", str(root), "--out", str(out), *SIZE], two_nodes.address
    )
    stdout, stderr = driver.communicate(timeout=300)
    assert driver.returncode == 1, stderr
    failed = [line for line in stderr.splitlines() if line.startswith("failed: ")]
    assert len(failed) == 1 and f"co3d/hydrant/{sequence}" in failed[0]
    assert "1 failed; the rest is made" in stderr
    assert sum(1 for _ in out.rglob("*.safetensors")) == 79
    assert "Traceback" not in stdout + stderr


@pytest.fixture(scope="module")
def dpt(tmp_path_factory) -> str:
    """A tiny random DPT (DINOv2 backbone) saved as a local model folder (tests/test_estimate_depth.py)."""
    pytest.importorskip("transformers", reason="the depth tool's optional extra: pip install -e '.[depth]'")
    from tests.test_estimate_depth import tiny_dpt

    return tiny_dpt(tmp_path_factory.mktemp("dpt"))


def test_all_makes_every_input_says_what_remains_and_asks_for_msns_weights(two_nodes, co3d, one_process, dpt, tmp_path):
    from tests.test_encoder import write_msn_checkpoint

    inputs_dir, out = tmp_path / "inputs", tmp_path / "prepared"
    args = ["all", "--set", "data.kind=co3d", "--root", str(co3d), "--out", str(out), "--inputs", str(inputs_dir),
            "--model", dpt, *SIZE]
    first = _driver(args, two_nodes.address)
    stdout, stderr = first.communicate(timeout=600)
    assert first.returncode == 2, stderr
    assert "MSN weights: missing; shards: 0 in" in stdout and "views: to export; depth maps: 0 in" in stdout
    assert f"error: MSN's weights: {inputs_dir / 'msn' / 'vits16_800ep.pth.tar'} is missing: curl -L" in stderr
    assert _files(out) == _files(one_process)
    maps = sorted(p.relative_to(inputs_dir / "depth_maps") for p in (inputs_dir / "depth_maps").rglob("*.npy"))
    crops = sorted(p.relative_to(inputs_dir / "views" / "co3d").with_suffix(".npy")
                   for p in (inputs_dir / "views" / "co3d").rglob("*.png") if p.stem.isdigit())
    assert maps == crops and len(maps) == 80 * 3

    (inputs_dir / "msn").mkdir()
    write_msn_checkpoint(inputs_dir / "msn" / "vits16_800ep.pth.tar")
    again = _driver(args, two_nodes.address)
    stdout, stderr = again.communicate(timeout=300)
    assert again.returncode == 0, stderr
    assert "MSN weights: present; shards: 80 in" in stdout and f"views: exported; depth maps: {len(maps)} in" in stdout
    assert "0 shards written, 80 already complete" in stdout and f"0 written, {len(maps)} already there" in stdout
    assert "sha256" in stdout and "Traceback" not in stdout + stderr
