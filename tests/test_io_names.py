"""cdm/io/names.py: names and annotation paths that stay inside the data root."""

from __future__ import annotations

import pytest

from cdm.io.names import inside, object_id_parts, plain_name


@pytest.mark.parametrize(
    "path", ["../outside/x.jpg", "teddybear/../../x.jpg", "/etc/passwd", "\\\\server\\x", "C:/x", "", "a\0b"]
)
def test_an_annotation_path_leaving_the_root_is_refused(path):
    with pytest.raises(ValueError, match="^frame_annotations.jgz entry 3: image.path gives the path"):
        inside(path, "frame_annotations.jgz entry 3: image.path")


def test_an_annotation_path_below_the_root_is_kept():
    assert (
        inside("teddybear/101_11758_21048/images/frame000001.jpg", "x")
        == "teddybear/101_11758_21048/images/frame000001.jpg"
    )


@pytest.mark.parametrize("name", ["..", ".", "../../../ESCAPED", "a/b", ".hidden", "", "x" * 129, 7, None])
def test_a_name_that_is_not_one_plain_file_name_is_refused(name):
    with pytest.raises(ValueError, match="expected a plain name"):
        plain_name(name, "sequence_annotations.jgz: sequence_name")


def test_object_ids_have_three_plain_parts():
    assert object_id_parts("co3d/teddybear/101_11758_21048", "m") == ["co3d", "teddybear", "101_11758_21048"]
    for bad in ("co3d/teddybear/../../../x", "co3d/x", "co3d/a/b/c"):
        with pytest.raises(ValueError):
            object_id_parts(bad, "m")
