"""The onboard commands' file handling, numpy only: a checked ``.npy`` cube in (``onboard.load_cube``: dtypes
converted alike, the frame cap from the header), a mask PNG out (shared by ``torchskin detect`` and
``torchskin calibrate``)."""

from __future__ import annotations

import os

import numpy as np

from ..io import write_png
from ..onboard import load_cube


def write_mask_png(path: str | os.PathLike, mask: np.ndarray) -> None:
    """A greyscale PNG of a boolean (H, W) mask (skin white), written atomically (``io.write_png``)."""
    write_png(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


__all__ = ["load_cube", "write_mask_png"]
