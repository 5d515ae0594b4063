"""YAML a user or a neighbour wrote (config files, ``--set`` values, sweep specs, profiles), read under one rule.

PyYAML's safe loader runs no code, but a YAML text can still cost: an alias chain of 330 bytes (a "billion
laughs") expands to gigabytes of nodes, brackets nested thousands deep overflow its recursive composer
(50,000 took 93 s to end in a ``RecursionError``), and an integer of 5,001 digits stops ``int()`` naming
nothing. Every YAML read in the project goes through :func:`read_yaml` or :func:`parse_yaml`, under one
rule (also in docs/security.md):

- a file is at most :data:`MAX_YAML_BYTES` of UTF-8 text (:func:`cdm.io.files.read_text`);
- brackets nest at most :data:`MAX_YAML_DEPTH` deep, counted before the parser sees the text;
- aliases (``*name``) are allowed, but the document with every alias expanded holds at most
  :data:`MAX_YAML_NODES` nodes, counted on the composed graph before anything is constructed;
- integers have at most :data:`cdm.io.json.MAX_INT_DIGITS` digits and dates exist (:class:`BoundedYamlLoader`).

Each refusal is one ``ValueError`` line starting with the caller's label.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from cdm.io.files import read_text
from cdm.io.json import MAX_INT_DIGITS, MAX_JSON_DEPTH, bracket_depth

__all__ = ["MAX_YAML_BYTES", "MAX_YAML_DEPTH", "MAX_YAML_NODES", "parse_yaml", "read_mapping", "read_yaml"]

MAX_YAML_BYTES = 1 << 20
"""Largest YAML file read (1 MiB; the repository's specs and configs are a few kB)."""
MAX_YAML_DEPTH = MAX_JSON_DEPTH
"""Deepest bracket (``[``, ``{``) nesting of a YAML text, as of JSON's (a config field needs two)."""
MAX_YAML_NODES = 100_000
"""Most YAML nodes a document may hold once its aliases are expanded."""


class BoundedYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader whose integers and dates fail as a ``yaml.YAMLError`` at their line and
    column: an integer of more than :data:`MAX_INT_DIGITS` digits (Python's ``int()`` stops at 4300
    naming nothing) or a date that does not exist (``2026-02-30``: a bare ``ValueError`` otherwise).
    Every reader of a YAML file or value (configs, ``--set``, sweep specs) loads with it."""


def _bounded_yaml_int(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> int:
    digits = sum(c.isdigit() for c in str(node.value))
    if digits > MAX_INT_DIGITS:
        raise yaml.constructor.ConstructorError(
            None, None, f"an integer of {digits} digits; numbers read here have at most {MAX_INT_DIGITS}",
            node.start_mark)
    return loader.construct_yaml_int(node)


def _checked_yaml_timestamp(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> Any:
    try:
        return loader.construct_yaml_timestamp(node)
    except ValueError as exc:
        raise yaml.constructor.ConstructorError(None, None, f"{node.value!r} is no date ({exc})",
                                                node.start_mark) from None


BoundedYamlLoader.add_constructor("tag:yaml.org,2002:int", _bounded_yaml_int)
BoundedYamlLoader.add_constructor("tag:yaml.org,2002:timestamp", _checked_yaml_timestamp)


class _SelfReference(Exception):
    """An anchor whose own value refers to it through an alias."""


def _expanded_size(node: yaml.Node, memo: dict[int, int], active: set[int]) -> int:
    """Nodes under ``node`` with every alias expanded (shared nodes counted once per use), counted no
    further than past :data:`MAX_YAML_NODES`."""
    key = id(node)
    if key in memo:
        return memo[key]
    if key in active:
        raise _SelfReference
    active.add(key)
    if isinstance(node, yaml.SequenceNode):
        children = list(node.value)
    elif isinstance(node, yaml.MappingNode):
        children = [part for pair in node.value for part in pair]
    else:
        children = []
    size = 1
    for child in children:
        size += _expanded_size(child, memo, active)
        if size > MAX_YAML_NODES:
            break
    active.discard(key)
    memo[key] = size
    return size


def parse_yaml(text: str, label: str) -> Any:
    """``text`` as YAML under the module's rule: what ``yaml.safe_load`` gives, or a ``ValueError``
    starting with ``label`` (what the text is: ``"config file x.yaml"``, ``"data.categories: the value"``)."""
    if (depth := bracket_depth(text.encode(errors="replace"))) > MAX_YAML_DEPTH:  # before the recursive parser
        raise ValueError(f"{label} is nested {depth} deep; at most {MAX_YAML_DEPTH}")
    loader = BoundedYamlLoader(text)
    try:
        node = loader.get_single_node()
        size = 0 if node is None else _expanded_size(node, {}, set())
        value = loader.construct_document(node) if node is not None and size <= MAX_YAML_NODES else None
    except yaml.YAMLError as exc:
        raise ValueError(f"{label} is not valid YAML: {' '.join(str(exc).split())}") from None
    except _SelfReference:
        raise ValueError(f"{label} refers to itself through an alias (a recursive anchor)") from None
    except RecursionError:  # block-style nesting, which no bracket counts
        raise ValueError(f"{label} is nested too deeply to be read") from None
    except ValueError as exc:  # a value PyYAML builds but Python refuses
        raise ValueError(f"{label} is not valid YAML: {exc}") from None
    finally:
        loader.dispose()
    if size > MAX_YAML_NODES:
        raise ValueError(f"{label}: its aliases (*name) expand to more than {MAX_YAML_NODES} YAML nodes; "
                         "write the values out or use fewer nested aliases")
    return value


def read_yaml(path: Path, label: str) -> Any:
    """The YAML file ``path`` under the module's rule (:func:`parse_yaml`); a ``ValueError`` starting with
    ``label`` (the field or option that named the file) and the path."""
    return parse_yaml(read_text(path, label, MAX_YAML_BYTES), f"{label}: {path}")


def read_mapping(path: Path, label: str) -> dict[str, Any]:
    """The YAML file ``path`` (:func:`read_yaml`) as a mapping, ``{}`` when it is empty; a ``ValueError``
    starting with ``label`` and the path when its top level is anything else."""
    tree = read_yaml(path, label)
    if tree is None:
        return {}
    if not isinstance(tree, dict):
        raise ValueError(f"{label}: {path}: top level must be a mapping, not a {type(tree).__name__}")
    return tree
