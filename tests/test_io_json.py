"""cdm/io/json.py: JSON nesting and integer digits bounded before the parser sees them."""

from __future__ import annotations

import json

import pytest

from cdm.io.json import MAX_JSON_DEPTH, parse_json, read_json
from tests.hostile_files import nested_json


def test_json_nested_past_the_cap_is_refused_before_the_parser_sees_it(tmp_path):
    path = tmp_path / "set_list.json"
    with pytest.raises(ValueError, match=f"nests 100000 levels deep; JSON read here may nest at most {MAX_JSON_DEPTH}"):
        parse_json(nested_json(100_000).encode(), "data.root", path)
    at_cap = "[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH
    assert parse_json(at_cap.encode(), "data.root", path) == json.loads(at_cap)
    # Brackets inside strings (escaped quotes too) are text, not nesting.
    text = json.dumps({"name": "[[[[" * 100 + '\\"' + "{{" * 100, "list": [[1]]})
    assert parse_json(text.encode(), "data.root", path)["list"] == [[1]]


def test_json_that_is_not_utf8_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "pc_dict_v2.json"
    path.write_bytes(b'{"train": "\xff\xfe"}')
    with pytest.raises(ValueError, match=f"data.root: {path} is not JSON"):
        read_json(path, "data.root")
