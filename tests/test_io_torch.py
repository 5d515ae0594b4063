"""Torch files read as tensors and plain data only: what loads, the refusals in our words, and a config read
as inert records."""

from __future__ import annotations

import argparse

import pytest
import torch

from cdm.io.torch import Pickled, load_inert, load_tensors, pickle_bytes


def _load(file):
    return load_tensors(file, f"weights: {file}", "weights file", "Pass the weights alone.")


def test_tensors_and_plain_data_load_on_the_cpu(tmp_path):
    torch.save({"w": torch.arange(3.0), "step": 7, "names": ["a"]}, tmp_path / "ok.pt")
    loaded = _load(tmp_path / "ok.pt")
    assert torch.equal(loaded["w"], torch.arange(3.0)) and loaded["w"].device.type == "cpu"
    assert (loaded["step"], loaded["names"]) == (7, ["a"])


def test_pickled_objects_garbage_and_a_truncated_archive_are_refused_apart(tmp_path):
    torch.save({"cfg": argparse.Namespace(code=1)}, tmp_path / "objects.pt")
    with pytest.raises(ValueError, match=r"^weights: .*objects\.pt holds Python objects other than tensors .* "
                                         r"could run code from the file\. Pass the weights alone\.$") as refused:
        _load(tmp_path / "objects.pt")
    assert "weights_only" not in str(refused.value)  # torch's own advice would run the file's code
    (tmp_path / "garbage.pt").write_bytes(b"not a torch file")
    with pytest.raises(
        ValueError, match=r"^weights: .*garbage\.pt is not a readable weights file: not in torch's file format$"
    ):
        _load(tmp_path / "garbage.pt")
    torch.save({"w": torch.zeros(1000)}, tmp_path / "cut.pt")
    (tmp_path / "cut.pt").write_bytes((tmp_path / "cut.pt").read_bytes()[:600])
    with pytest.raises(ValueError, match=r"^weights: .*cut\.pt is not a readable weights file: not in torch's "):
        _load(tmp_path / "cut.pt")


class _Payload:
    def __init__(self, call, *args):
        self.call, self.args = call, args

    def __reduce__(self):
        return self.call, self.args


def test_load_inert_keeps_tensors_and_makes_a_config_a_record_without_importing_it(tmp_path):
    import sys

    from tests.pc2_files import fake_omegaconf

    with fake_omegaconf() as modules:
        node_type = type("IntegerNode", (), {"__module__": "omegaconf.nodes", "__qualname__": "IntegerNode"})
        modules["omegaconf.nodes"].IntegerNode = node_type
        node = node_type()
        node.__dict__.update(_val=224, _parent=None)
        torch.save({"w": torch.arange(3.0), "cfg": {"image_size": node}}, tmp_path / "pc2.pth")
    loaded = load_inert(tmp_path / "pc2.pth", "x", "y")
    assert torch.equal(loaded["w"], torch.arange(3.0))
    record = loaded["cfg"]["image_size"]
    assert isinstance(record, Pickled) and record.name == "omegaconf.nodes.IntegerNode"
    assert record.state == {"_val": 224, "_parent": None} and "omegaconf.nodes" not in sys.modules


@pytest.mark.parametrize("call,args,names", [
    ("os.system", ("touch {marker}",), "posix.system"),
    ("builtins.eval", ("open({marker!r}, 'w')",), "builtins.eval"),
    ("builtins.exec", ("open({marker!r}, 'w')",), "builtins.exec"),
    ("subprocess.call", (["touch", "{marker}"],), "subprocess.call"),
])
def test_load_inert_refuses_a_reduce_payload_and_runs_nothing(tmp_path, call, args, names):
    import builtins
    import importlib

    marker = tmp_path / "marker"
    module, name = call.rsplit(".", 1)
    func = getattr(builtins if module == "builtins" else importlib.import_module(module), name)
    filled = tuple(
        [a.format(marker=str(marker)) for a in arg] if isinstance(arg, list) else arg.format(marker=str(marker))
        for arg in args
    )
    torch.save({"model": {"w": torch.zeros(2)}, "cfg": {"run": _Payload(func, *filled)}}, tmp_path / "bad.pth")
    with pytest.raises(
        ValueError,
        match=rf"^weights: .*bad\.pth could run code from the file while loading \(it calls {names}\); "
        "refused, and nothing of it was run",
    ):
        load_inert(tmp_path / "bad.pth", f"weights: {tmp_path / 'bad.pth'}", "weights file")
    assert not marker.exists()


def test_load_inert_refuses_what_is_not_a_torch_archive(tmp_path):
    (tmp_path / "garbage.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"garbage\.pt is not a readable weights file: not in torch's file format$"):
        load_inert(tmp_path / "garbage.pt", f"weights: {tmp_path / 'garbage.pt'}", "weights file")


def test_pickle_bytes_are_the_archives_pickle_unpickled_by_no_one(tmp_path):
    path = tmp_path / "w.pt"
    torch.save({"point_cloud_model.weight": torch.zeros(2)}, path)
    raw = pickle_bytes(path, str(path))
    assert raw.startswith(b"\x80") and b"point_cloud_model.weight" in raw
    torch.save({"point_cloud_model.weight": torch.zeros(2)}, path, _use_new_zipfile_serialization=False)
    assert b"point_cloud_model.weight" in pickle_bytes(path, str(path))  # a pre-zip file's pickles come first
    path.write_bytes(b"not a zip at all")
    with pytest.raises(ValueError, match=f"^{path} is not in torch's file format"):
        pickle_bytes(path, str(path))
