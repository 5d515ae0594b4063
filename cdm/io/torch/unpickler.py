"""The inert unpickler of :mod:`cdm.io.torch`: a ``data.pkl`` turned into tensors, plain data and records.

Built on the pure-Python :class:`pickle._Unpickler` so that every opcode that calls, fills or mutates an
object can be replaced: REDUCE calls only torch's tensor rebuilding (done here, after checking its
arguments), ``OrderedDict()``, ``torch.Size(ints)`` and record classes; BUILD, SETITEM(S), APPEND(S) and
ADDITEMS fill only records and the plain containers the pickle built; INST and OBJ are refused. Every
opcode counts against :data:`MAX_PICKLE_OPS`, and the result's nesting is checked without recursion
against :data:`MAX_NESTING` before any caller walks it.
"""

from __future__ import annotations

import _compat_pickle
import pickle
import types
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO, Any, Protocol

import torch

from cdm.io.torch.archive import ArchiveError

__all__ = ["CONFIG_CALLS", "MAX_NESTING", "MAX_PICKLE_OPS", "PICKLE_DAMAGE", "Pickled", "Refused", "Storages",
           "unpickle"]

MAX_PICKLE_OPS = 2_000_000
"""Most opcodes one ``data.pkl`` may run: each builds at most one object. PC²'s checkpoint needs tens of
thousands (about twenty per tensor, a few per config node); a 98 kB archive of a 10⁸-element list needs 10⁸."""
MAX_NESTING = 100
"""Most nesting of containers and records in a pickle (PC²'s cfg nests about 20 deep as OmegaConf
pickles it); deeper ones would overflow the recursion of whoever walks the result."""

CONFIG_CALLS = ("omegaconf.*", "collections.defaultdict", "builtins.type", "builtins.set", "builtins.frozenset",
                "_operator.getitem", "operator.getitem")
"""What a pickled config may call, each call kept as a record: OmegaConf's containers, nodes and
metadata (created bare, then given their state), the ``defaultdict`` of its resolver cache, and what
type annotations pickle through (``type(None)``, ``typing.Optional[int]`` as ``getitem``)."""
PICKLE_DAMAGE = (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, IndexError, RuntimeError,
                 AttributeError)
"""What a malformed pickle raises (a bad opcode, a stack underflow, an unhashable key): damage, not a payload
(:class:`Refused`, a payload, is an ``UnpicklingError`` too: catch it first)."""


class Storages(Protocol):
    """Where a pickle's storages come from: a zip :class:`cdm.io.torch.archive.Archive` or a legacy file."""

    byteorder: str
    STORAGE_ID: tuple[str, ...]
    """The fields of a persistent id after ``'storage'``."""

    def storage(self, key: str, nbytes: int) -> torch.Tensor:
        """Storage ``key`` as a uint8 tensor of exactly ``nbytes``."""


class Refused(pickle.UnpicklingError):
    """The pickle calls or builds something a file of tensors, plain data and a config does not."""


class Pickled:
    """An object a file pickled, kept as data: ``name`` (its class's dotted name), the ``args`` it was
    created with, the ``state`` pickle gave it, and the ``items`` / ``appended`` a container received."""

    name = ""
    callable_ = False

    def __new__(cls, *args: Any, **kwargs: Any) -> Pickled:
        if not cls.callable_:
            raise Refused(f"it calls {cls.name}")
        record = object.__new__(cls)
        record.args, record.state, record.items, record.appended = args, None, {}, []
        return record

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """Pickle calls the class with the arguments already kept by ``__new__``."""

    def __repr__(self) -> str:
        return f"Pickled({self.name})"


@dataclass(frozen=True)
class _Storage:
    """A storage record of the archive, typed as its persistent id says."""

    dtype: torch.dtype
    data: torch.Tensor  # uint8, the record's bytes

    @property
    def numel(self) -> int:
        return self.data.numel() // self.dtype.itemsize


_STORAGE_TYPES = {f"torch.{name}": dtype for dtype, name in torch.storage._dtype_to_storage_type_map().items()}
_VALUES = {f"torch.{name}": value for name, value in vars(torch).items() if isinstance(value, torch.dtype)}


def _ints(value: Any, what: str) -> tuple[int, ...]:
    if not (isinstance(value, tuple) and all(type(v) is int and v >= 0 for v in value)):
        raise ArchiveError(f"its pickle gives a tensor {what} that is not a tuple of non-negative ints")
    return value


def _no_hooks(hooks: Any) -> None:
    if not (type(hooks) in (dict, OrderedDict) and not hooks):
        raise Refused("it gives a tensor backward hooks")


def _tensor(storage: Any, offset: Any, size: Any, stride: Any, requires_grad: Any = False, hooks: Any = None,
            metadata: Any = None) -> torch.Tensor:
    """``torch._utils._rebuild_tensor_v2``'s work, on checked arguments, without calling it."""
    if not isinstance(storage, _Storage) or type(offset) is not int or offset < 0 or type(requires_grad) is not bool:
        raise ArchiveError("its pickle rebuilds a tensor from arguments torch.save does not write")
    size, stride = _ints(size, "size"), _ints(stride, "stride")
    if hooks is not None:
        _no_hooks(hooks)
    if metadata:
        raise Refused("it gives a tensor metadata")
    if len(size) != len(stride):
        raise ArchiveError(f"its pickle gives a tensor {len(size)} sizes and {len(stride)} strides")
    end = offset + sum((n - 1) * s for n, s in zip(size, stride)) + 1 if all(size) else offset
    if end > storage.numel:
        raise ArchiveError(f"its pickle reads a tensor past the end of its storage ({end:,} > {storage.numel:,})")
    tensor = torch.empty((0,), dtype=storage.dtype).set_(storage.data.untyped_storage(), offset, size, stride)
    tensor.requires_grad_(requires_grad)
    return tensor


def _tensor_v1(storage: Any, offset: Any, size: Any, stride: Any) -> torch.Tensor:
    return _tensor(storage, offset, size, stride)


def _parameter(data: Any, requires_grad: Any, hooks: Any, state: Any = None) -> torch.nn.Parameter:
    if type(data) is not torch.Tensor or type(requires_grad) is not bool:
        raise ArchiveError("its pickle rebuilds a parameter from arguments torch.save does not write")
    _no_hooks(hooks)
    if state:
        raise Refused("it gives a parameter attributes")
    return torch.nn.Parameter(data, requires_grad)


def _ordered_dict() -> OrderedDict:
    return OrderedDict()


def _size(dims: Any) -> torch.Size:
    return torch.Size(_ints(dims, "size"))


_CALLS: dict[str, Callable[..., Any]] = {
    "torch._utils._rebuild_tensor": _tensor_v1,
    "torch._utils._rebuild_tensor_v2": _tensor,
    "torch._utils._rebuild_parameter": _parameter,
    "torch._utils._rebuild_parameter_with_state": _parameter,
    "torch.Size": _size,
    "collections.OrderedDict": _ordered_dict,
}
"""What a tensor file calls, as torch's weights-only reader allows it, each by our own checked stand-in."""


@dataclass(frozen=True)
class _Call:
    """A callable the pickle named (GLOBAL): only REDUCE may call it, through :data:`_CALLS`."""

    name: str


def _may_call(name: str) -> bool:
    return any(
        name == allowed or (allowed.endswith(".*") and name.startswith(allowed[:-1])) for allowed in CONFIG_CALLS
    )


def _counted(step: Callable[[Any], None]) -> Callable[[Any], None]:
    def run(self: _Unpickler) -> None:
        self.ops += 1
        if self.ops > MAX_PICKLE_OPS:
            raise ArchiveError(f"its pickle runs more than {MAX_PICKLE_OPS:,} steps")
        step(self)

    return run


class _Unpickler(pickle._Unpickler):
    """``data.pkl`` as tensors, plain data and (with ``records``) :class:`Pickled` records."""

    def __init__(self, file: IO[bytes], archive: Storages, records: bool) -> None:
        super().__init__(file)
        self.archive, self.records, self.ops = archive, records, 0
        self.classes: dict[str, type[Pickled]] = {}

    def find_class(self, module: str, name: str) -> Any:
        # Protocol 2 writes Python 2's names (``__builtin__.unicode``); map them as pickle itself does.
        module, name = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
        full = f"{_compat_pickle.IMPORT_MAPPING.get(module, module)}.{name}"
        if full in _CALLS:
            return _Call(full)
        if full in _STORAGE_TYPES:
            return _STORAGE_TYPES[full]
        if full in _VALUES:
            return _VALUES[full]
        if not self.records:
            raise Refused(f"it names {full}")
        if full not in self.classes:
            self.classes[full] = types.new_class(name, (Pickled,), exec_body=lambda ns: ns.update(
                name=full, callable_=_may_call(full)))
        return self.classes[full]

    def persistent_load(self, pid: Any) -> _Storage:
        form = self.archive.STORAGE_ID
        if not (type(pid) is tuple and len(pid) == 1 + len(form) and pid[0] == "storage"):
            raise ArchiveError(f"its pickle names a storage as {_short(pid)}; torch.save writes "
                               f"('storage', {', '.join(form)})")
        _, dtype, key, _location, numel = pid[:5]
        if pid[5:] not in ((), (None,)):  # a legacy view, which torch.save has not written since torch 0.4
            raise ArchiveError(f"its pickle names a view of a storage, {_short(pid)}")
        if not isinstance(dtype, torch.dtype) or type(key) is not str or type(numel) is not int or numel < 0:
            raise ArchiveError(f"its pickle names a storage as {_short(pid)}, not (str, storage type, key, "
                               "location, size)")
        data = self.archive.storage(key, numel * dtype.itemsize)
        if self.archive.byteorder == "big" and dtype.itemsize > 1:
            data = data.view(-1, dtype.itemsize).flip(1).reshape(-1)
        return _Storage(dtype, data)

    def _reduce(self) -> None:
        args = self.stack.pop()
        func = self.stack[-1]
        if type(args) is not tuple:
            raise ArchiveError("its pickle calls with arguments that are not a tuple")
        if isinstance(func, _Call):
            self.stack[-1] = _CALLS[func.name](*args)
        elif isinstance(func, type) and issubclass(func, Pickled):
            self.stack[-1] = func(*args)
        else:
            raise Refused(f"it calls {_short(func)}")

    def _newobj(self) -> None:
        args = self.stack.pop()
        cls = self.stack.pop()
        if not (isinstance(cls, type) and issubclass(cls, Pickled)) or type(args) is not tuple:
            raise Refused(f"it creates {_short(cls)} bare")
        self.append(cls(*args))

    def _newobj_ex(self) -> None:
        kwargs = self.stack.pop()
        args = self.stack.pop()
        cls = self.stack.pop()
        if not (isinstance(cls, type) and issubclass(cls, Pickled)) or type(args) is not tuple \
                or type(kwargs) is not dict:
            raise Refused(f"it creates {_short(cls)} bare")
        self.append(cls(*args, **{str(k): v for k, v in kwargs.items()}))

    def _build(self) -> None:
        state = self.stack.pop()
        target = self.stack[-1]
        if isinstance(target, Pickled):
            target.state = state
        elif type(target) is OrderedDict and type(state) is dict and set(state) <= {"_metadata"}:
            target.__dict__.update(state)  # a state dict's ``_metadata`` (``nn.Module.state_dict``)
        else:
            raise Refused(f"it sets the state of {_short(target)}")

    def _setitems(self) -> None:
        items = self.pop_mark()
        self._fill(items[0::2], items[1::2])

    def _setitem(self) -> None:
        value = self.stack.pop()
        key = self.stack.pop()
        self._fill([key], [value])

    def _fill(self, keys: list[Any], values: list[Any]) -> None:
        target = self.stack[-1]
        if isinstance(target, Pickled):
            target = target.items
        elif type(target) not in (dict, OrderedDict):
            raise Refused(f"it sets items of {_short(target)}")
        target.update(zip(keys, values))

    def _appends(self) -> None:
        self._extend(self.pop_mark())

    def _append(self) -> None:
        self._extend([self.stack.pop()])

    def _extend(self, items: list[Any]) -> None:
        """APPEND(S): only onto a record or a list the pickle built."""
        target = self.stack[-1]
        if isinstance(target, Pickled):
            target.appended.extend(items)
        elif type(target) is list:
            target.extend(items)
        else:
            raise Refused(f"it appends to {_short(target)}")

    def _additems(self) -> None:
        items = self.pop_mark()
        if type(self.stack[-1]) is not set:
            raise Refused(f"it adds items to {_short(self.stack[-1])}")
        self.stack[-1].update(items)

    def _refuse(self) -> None:
        raise Refused("it creates an object through the old INST/OBJ opcodes")

    dispatch = dict(pickle._Unpickler.dispatch)
    dispatch.update({pickle.REDUCE[0]: _reduce, pickle.NEWOBJ[0]: _newobj, pickle.NEWOBJ_EX[0]: _newobj_ex,
                     pickle.BUILD[0]: _build, pickle.SETITEMS[0]: _setitems, pickle.SETITEM[0]: _setitem,
                     pickle.APPENDS[0]: _appends, pickle.APPEND[0]: _append, pickle.ADDITEMS[0]: _additems,
                     pickle.INST[0]: _refuse, pickle.OBJ[0]: _refuse})
    dispatch = {code: _counted(step) for code, step in dispatch.items()}


def _short(value: Any) -> str:
    if isinstance(value, _Call):
        return value.name
    text = repr(value) if isinstance(value, (str, bytes, int, float, tuple, type(None))) else type(value).__name__
    return text if len(text) <= 60 else f"{text[:57]}..."


def unpickle(file: IO[bytes], archive: Storages, records: bool) -> Any:
    """``data.pkl`` of ``archive`` read inertly; raises :class:`Refused` for what could run code and
    :class:`cdm.io.torch.archive.ArchiveError` for a broken cap or a malformed storage reference."""
    result = _Unpickler(file, archive, records).load()
    _check_nesting(result)
    return result


def _children(value: Any) -> list[Any]:
    if isinstance(value, Pickled):
        return [value.args, value.state, value.items, value.appended]
    if type(value) in (dict, OrderedDict):
        return [*value.keys(), *value.values(), *vars(value).values()] if type(value) is OrderedDict \
            else [*value.keys(), *value.values()]
    if type(value) in (list, tuple, set, frozenset):
        return list(value)
    return []


_CONTAINERS = (dict, OrderedDict, list, tuple, set, frozenset)


def _check_nesting(root: Any) -> None:
    """Refuse a result that nests deeper than :data:`MAX_NESTING`, by the longest path of containers
    (references back up the current path, OmegaConf's ``_parent``, are not followed), without recursion."""
    depth: dict[int, int] = {}
    path = {id(root)}
    stack = [(root, iter(_children(root)), [0])]
    while stack:
        value, children, best = stack[-1]
        child = next(children, stack)
        if child is stack:
            stack.pop()
            path.discard(id(value))
            depth[id(value)] = best[0]
            if stack:
                stack[-1][2][0] = max(stack[-1][2][0], best[0] + 1)
        elif type(child) in _CONTAINERS or isinstance(child, Pickled):
            if id(child) in depth:
                best[0] = max(best[0], depth[id(child)] + 1)
            elif id(child) not in path:
                path.add(id(child))
                stack.append((child, iter(_children(child)), [0]))
            if len(stack) > MAX_NESTING or best[0] > MAX_NESTING:
                raise ArchiveError(f"its pickle nests deeper than {MAX_NESTING} levels")
