"""cdm/io/images.py: an image's pixels after its header's size is checked; RGB for readers that want it."""

from __future__ import annotations

import cv2
import numpy as np

from cdm.io.images import read_image, read_rgb


def test_read_rgb_is_read_image_in_rgb_order_and_none_for_what_is_not_an_image(tmp_path):
    bgr = np.zeros((4, 6, 3), np.uint8)
    bgr[..., 0] = 200  # blue in OpenCV's order
    cv2.imwrite(str(tmp_path / "panel.png"), bgr)
    rgb = read_rgb(tmp_path / "panel.png", "evaluation panel")
    assert rgb.shape == (4, 6, 3) and rgb.flags.c_contiguous
    assert (rgb[..., 2] == 200).all() and (rgb[..., :2] == 0).all()
    assert np.array_equal(rgb[..., ::-1], read_image(tmp_path / "panel.png", cv2.IMREAD_COLOR, "f"))
    (tmp_path / "notes.png").write_text("not an image")
    assert read_rgb(tmp_path / "notes.png", "evaluation panel") is None
    assert read_rgb(tmp_path / "missing.png", "evaluation panel") is None
