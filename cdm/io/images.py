"""Reading a user's image files with the decoded size capped before anything is decoded.

A PNG's size is in its header, not in its bytes: a 130 KB 1-bit PNG of 32,768² pixels decodes to
gigabytes, and a 16-bit one asks OpenCV for 8.6 GB at once (then a bare ``cv2.error``). So
:func:`read_image` reads the header first (PIL opens a file lazily: size and mode, no pixels) and
refuses more than :data:`MAX_IMAGE_PIXELS` pixels, naming the file, its size and what decoding it
would take, before OpenCV decodes it. The file is opened once (:func:`cdm.io.files.open_regular`: a
FIFO or device is refused, not read) and both the header and the pixels come from the bytes read.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from cdm.io.arrays import MAX_ARRAY_BYTES
from cdm.io.files import read_bounded

__all__ = ["MAX_IMAGE_PIXELS", "read_image", "read_rgb"]

MAX_IMAGE_PIXELS = 1 << 26
"""Most pixels (width × height) of an image read: 8,192² (Co3D's frames are about 2 megapixels)."""

_BYTES_PER_PIXEL = {cv2.IMREAD_COLOR: 3, cv2.IMREAD_GRAYSCALE: 1, cv2.IMREAD_UNCHANGED: 8}
"""What OpenCV's decoded array takes per pixel under each flag; unchanged: at most 4 channels × 16 bits."""


def read_image(path: Path, flags: int, field: str) -> np.ndarray | None:
    """``cv2.imread(path, flags)``, after checking the header: ``(H, W)`` or ``(H, W, C)`` BGR(A) pixels,
    8- or 16-bit as OpenCV decodes them; None when the file is missing or not an image (as ``cv2.imread``).

    Args:
        path: the image file.
        flags: ``cv2.IMREAD_COLOR``, ``cv2.IMREAD_GRAYSCALE`` or ``cv2.IMREAD_UNCHANGED``.
        field: the config field or option that named the file, for the message.

    Raises:
        ValueError: the header says more than :data:`MAX_IMAGE_PIXELS` pixels, or ``path`` is not a
            regular file (a FIFO, a device, a folder) or is over :data:`cdm.io.files.MAX_ARRAY_BYTES`.
    """
    path = Path(path)
    if not path.exists():
        return None
    data = read_bounded(path, field, MAX_ARRAY_BYTES)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our own cap follows
            with Image.open(io.BytesIO(data)) as header:
                width, height = header.size
    except Image.DecompressionBombError:  # PIL's own cap (twice Image.MAX_IMAGE_PIXELS) refused the header
        _refuse(field, path, f"over {2 * Image.MAX_IMAGE_PIXELS} pixels")
    except (OSError, UnidentifiedImageError):
        return None
    if width * height > MAX_IMAGE_PIXELS:
        need = width * height * _BYTES_PER_PIXEL[flags]
        _refuse(field, path, f"{width}×{height} pixels (decoding takes {need / 2**30:.1f} GiB)")
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags)


def read_rgb(path: Path, field: str) -> np.ndarray | None:
    """The image at ``path`` as ``(H, W, 3)`` 8-bit RGB, read as :func:`read_image` reads it (header first,
    regular files only); None when the file is missing or not an image."""
    bgr = read_image(path, cv2.IMREAD_COLOR, field)
    return None if bgr is None else np.ascontiguousarray(bgr[..., ::-1])


def _refuse(field: str, path: Path, size: str) -> None:
    raise ValueError(f"{field}: {path} is {size}; an image may have at most {MAX_IMAGE_PIXELS} pixels "
                     "(8192×8192): scale it down")
