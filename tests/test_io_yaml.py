"""cdm/io/yaml.py: one bounded rule for every YAML read (config files, ``--set`` values, specs, profiles):
size, bracket nesting, aliases counted as expanded, integer digits."""

from __future__ import annotations

import tracemalloc

import pytest
import yaml

from cdm.config import ConfigError, load_config, parse_override
from cdm.io.yaml import MAX_YAML_DEPTH, parse_yaml, read_mapping, read_yaml
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import load_spec
from tests.hostile_files import YAML_BOMB


def test_alias_bomb_is_refused_before_it_expands(tmp_path):
    spec = tmp_path / "bomb.yaml"
    spec.write_text(YAML_BOMB)
    assert len(YAML_BOMB) < 400
    tracemalloc.start()
    with pytest.raises(ValueError, match="expand to more than 100000 YAML nodes"):
        read_yaml(spec, "spec")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20 * 2**20  # the composed graph is a few hundred nodes; expansion would be gigabytes


def test_small_aliases_load_as_safe_load_does(tmp_path):
    text = "base: &b {priors.point_size: 0.04}\ngrid: {priors.lambda_3d: [0.1, 1.0]}\ncells: [{label: one, set: *b}]\n"
    spec = tmp_path / "s.yaml"
    spec.write_text(text)
    assert read_yaml(spec, "spec") == yaml.safe_load(text)


def test_recursive_anchor_binary_and_oversized_files_are_refused(tmp_path):
    cases = {"rec.yaml": (b"a: &x [1, *x]\n", "refers to itself"),
             "bin.yaml": (b"\x00\xff\xfe\x00 spec", "not UTF-8 text"),
             "big.yaml": (b"# " + b"x" * (1 << 20) + b"\n", "at most 1048576 are read")}
    for name, (data, needle) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=needle):
            read_yaml(tmp_path / name, "spec")


def test_the_one_rule_holds_for_a_config_file_a_set_value_and_a_spec_alike(tmp_path):
    """An alias bomb is refused, and a small alias read, by each reader of YAML: config file, ``--set``, spec."""
    config = tmp_path / "config.yaml"
    config.write_text("data:\n  categories: " + _bomb_value() + "\n")
    with pytest.raises(ConfigError, match=f"^config file: {config}: its aliases"):
        load_config(config)
    config.write_text("data:\n  categories: [&c chair, *c]\n")
    assert load_config(config).data.categories == ("chair", "chair")
    spec = tmp_path / "bomb.yaml"
    spec.write_text(YAML_BOMB)
    with pytest.raises(SpecError, match=f"^spec: {spec}: its aliases"):
        load_spec(spec)
    with pytest.raises(ConfigError, match="^data.categories: the value: its aliases"):
        parse_override("data.categories=" + _bomb_value())
    assert parse_override("data.categories=[&c chair, *c]") == ("data.categories", ["chair", "chair"])


def _bomb_value() -> str:
    """A one-line YAML flow value whose aliases expand to over 9⁶ ≈ 531,441 nodes."""
    parts = ["&a0 [x, x, x, x, x, x, x, x, x]"]
    parts += [f"&a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 7)]
    return "[" + ", ".join(parts) + "]"


@pytest.mark.parametrize(("text", "said"), [
    ("[" * 100 + "]" * 100, f"^v is nested 100 deep; at most {MAX_YAML_DEPTH}$"),
    ("9" * 5001, "^v is not valid YAML: .*an integer of 5001 digits"),
    ("when: 2026-02-30", "^v is not valid YAML: .*is no date"),
    ("a: [1\n", "^v is not valid YAML"),
    ("a: &x [1, *x]", "^v refers to itself through an alias"),
])
def test_parse_yaml_refuses_in_one_line_naming_the_label(text, said):
    with pytest.raises(ValueError, match=said) as refused:
        parse_yaml(text, "v")
    assert "\n" not in str(refused.value)


def test_read_mapping_is_a_mapping_or_one_line_and_an_empty_file_is_empty(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("")
    assert read_mapping(path, "spec") == {}
    path.write_text("- a\n- b\n")
    with pytest.raises(ValueError, match=f"^spec: {path}: top level must be a mapping, not a list$"):
        read_mapping(path, "spec")
    path.write_text("name: t\n")
    assert read_mapping(path, "spec") == {"name": "t"}
