"""Tools for picture tests: decode PNG bytes independently of the code under test."""

from __future__ import annotations

import io
import struct

import numpy as np
from matplotlib.image import imread

from app.vlp.typing import FloatArray

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(png: bytes) -> tuple[int, int]:
    """``(width, height)`` from the IHDR chunk, checking the signature on the way."""
    assert png[:8] == PNG_SIGNATURE
    assert png[12:16] == b"IHDR"
    width, height = struct.unpack(">II", png[16:24])
    return int(width), int(height)


def decode(png: bytes) -> FloatArray:
    """Pixels as floats in [0, 1], shape (height, width, channels)."""
    return np.asarray(imread(io.BytesIO(png), format="png"), dtype=np.float64)
