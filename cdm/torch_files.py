"""Torch files a user or a neighbour could have written, read as tensors and plain data only.

Two readers, neither of which runs code from the file:

- :func:`load_tensors`: ``torch.load(weights_only=True)``; a file that pickles other objects is refused
  in our words, since torch's own message advises ``weights_only=False``, i.e. running the file's code.
- :func:`load_inert`: for files that also pickle a config object, as PC²'s ``checkpoint-latest.pth``
  pickles its OmegaConf ``cfg`` (``experiments/main.py``). Tensors load as tensors; every other pickled
  object becomes a :class:`Pickled` record of its class name, arguments and state. No class is imported
  and nothing the pickle names is called, so a ``__reduce__`` payload cannot run. A file whose pickle
  calls anything but what a config pickles through (:data:`CONFIG_CALLS`) is refused all the same, so a
  payload is reported, not silently kept as data.
"""

from __future__ import annotations

import _compat_pickle
import pickle
import types
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import torch

from cdm.safe_io import open_regular

__all__ = ["CONFIG_CALLS", "Pickled", "load_inert", "load_tensors"]


def load_tensors(file: Path, label: str, kind: str, advice: str) -> Any:
    """``file``'s contents on the CPU, tensors and plain data only.

    Args:
        file: the torch file.
        label: how the refusal starts: the field and the path, e.g. ``"checkpoint: /runs/a/checkpoint.pt"``.
        kind: what an unreadable file is not, e.g. ``"CDM checkpoint"``.
        advice: the sentence after a refusal of pickled objects: what to pass instead.

    Raises:
        ValueError: the file pickles other objects, torch cannot read it, or it is not a regular file (a
            FIFO, a device such as ``/dev/zero``, a folder: refused before a byte is read); the message
            starts with ``label``.
    """
    with open_regular(file, label, show_path=False) as f:
        return _load(f, label, kind, advice)


def _load(f, label: str, kind: str, advice: str) -> Any:
    try:
        return torch.load(f, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch.save writes a zip archive; what is not one is not a torch file at all, pickled objects or not.
        f.seek(0)
        if not zipfile.is_zipfile(f):
            raise ValueError(f"{label} is not a readable {kind}: not in torch's file format") from None
        raise ValueError(f"{label} holds Python objects other than tensors and plain data; refused, since loading "
                         f"them could run code from the file. {advice}") from None
    except (RuntimeError, EOFError) as exc:
        raise ValueError(f"{label} is not a readable {kind} ({exc})") from None


CONFIG_CALLS = ("omegaconf.*", "collections.defaultdict", "builtins.type", "builtins.set", "builtins.frozenset",
                "_operator.getitem", "operator.getitem")
"""What a pickled config may call, each call kept as a record: OmegaConf's containers, nodes and
metadata (created bare, then given their state), the ``defaultdict`` of its resolver cache, and what
type annotations pickle through (``type(None)``, ``typing.Optional[int]`` as ``getitem``)."""

# What tensors and state dicts need, as torch's own weights-only reader allows them.
_REAL = {
    "torch._utils._rebuild_tensor": torch._utils._rebuild_tensor,
    "torch._utils._rebuild_tensor_v2": torch._utils._rebuild_tensor_v2,
    "torch._utils._rebuild_parameter": torch._utils._rebuild_parameter,
    "torch._utils._rebuild_parameter_with_state": torch._utils._rebuild_parameter_with_state,
    "torch.Size": torch.Size,
    "collections.OrderedDict": OrderedDict,
    **{f"torch.{name}": value for name, value in vars(torch).items() if isinstance(value, torch.dtype)},
}


class Pickled:
    """An object a file pickled, kept as data: ``name`` (its class's dotted name), the ``args`` it was
    created with, the ``state`` pickle gave it, and the ``items`` / ``appended`` a container received."""

    name = ""
    callable_ = False

    def __new__(cls, *args: Any, **kwargs: Any) -> Pickled:
        if not cls.callable_:
            raise pickle.UnpicklingError(f"it calls {cls.name}")
        record = object.__new__(cls)
        record.args, record.state, record.items, record.appended = args, None, {}, []
        return record

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """Pickle calls the class with the arguments already kept by ``__new__``."""

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def __setitem__(self, key: Any, value: Any) -> None:
        self.items[key] = value

    def append(self, value: Any) -> None:
        self.appended.append(value)

    def extend(self, values: Any) -> None:
        self.appended.extend(values)

    def __repr__(self) -> str:
        return f"Pickled({self.name})"


def _may_call(name: str) -> bool:
    return any(
        name == allowed or (allowed.endswith(".*") and name.startswith(allowed[:-1])) for allowed in CONFIG_CALLS
    )


class _InertUnpickler(pickle.Unpickler):
    """Resolves a name to a real object only for tensors (:data:`_REAL`), else to a :class:`Pickled` class."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._records: dict[str, type[Pickled]] = {}

    def find_class(self, module: str, name: str) -> Any:
        # Protocol 2 writes Python 2's names (``__builtin__.unicode``); map them as pickle itself does.
        module, name = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        full = f"{module}.{name}"
        if full in _REAL:
            return _REAL[full]
        if full not in self._records:
            self._records[full] = types.new_class(name, (Pickled,), exec_body=lambda ns: ns.update(
                name=full, callable_=_may_call(full)))
        return self._records[full]


# What torch.load takes as its pickle module: it subclasses ``Unpickler`` and adds its storage reading.
_inert_pickle = types.SimpleNamespace(Unpickler=_InertUnpickler, load=None, __name__="cdm.torch_files.inert")


def load_inert(file: Path, label: str, kind: str) -> Any:
    """``file``'s contents on the CPU: tensors as tensors, other objects as :class:`Pickled` records.

    Raises:
        ValueError: the file's pickle calls something outside :data:`CONFIG_CALLS` (nothing of it was
            run), or it is not a torch zip archive, or torch cannot read it, or it is not a regular file;
            the message starts with ``label``.
    """
    with open_regular(file, label, show_path=False) as f:
        if not zipfile.is_zipfile(f):
            raise ValueError(f"{label} is not a readable {kind}: not in torch's file format")
        f.seek(0)
        return _load_inert(f, label, kind)


def _load_inert(f, label: str, kind: str) -> Any:
    try:
        # weights_only=False only because torch takes a pickle module on no other terms: every name the
        # file's pickle resolves goes through _InertUnpickler.find_class, which returns no callable but
        # torch's tensor rebuilders and records.
        return torch.load(f, map_location="cpu", weights_only=False, pickle_module=_inert_pickle)
    except pickle.UnpicklingError as exc:
        raise ValueError(
            f"{label} could run code from the file while loading ({exc}); refused, and nothing of it was run. "
            f"Only tensors, plain data and a config ({', '.join(CONFIG_CALLS)}) are read"
        ) from None
    except (RuntimeError, EOFError, TypeError, AttributeError) as exc:
        raise ValueError(f"{label} is not a readable {kind} ({exc})") from None
