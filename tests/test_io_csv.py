"""cdm/io/csv.py: a CSV table read whole within the text cap, rows by the header's names."""

from __future__ import annotations

import pytest

from cdm.io.csv import read_csv


def test_rows_by_header_and_a_table_that_is_not_a_regular_file_or_text(tmp_path):
    path = tmp_path / "objects.csv"
    path.write_text('object_id,cd\n"a,1",0.5\nb,0.25\n')
    assert read_csv(path, "evaluation") == [{"object_id": "a,1", "cd": "0.5"}, {"object_id": "b", "cd": "0.25"}]
    path.write_bytes(b"object_id\n\xff\n")
    with pytest.raises(ValueError, match=f"^evaluation: {path} is not UTF-8 text"):
        read_csv(path, "evaluation")
    with pytest.raises(ValueError, match="is a folder"):
        read_csv(tmp_path, "evaluation")
