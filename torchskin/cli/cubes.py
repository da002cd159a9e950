"""The onboard commands' file handling, numpy only: a checked ``.npy`` cube in (``onboard.load_cube``: dtypes
converted alike, the frame cap from the header), a mask PNG out (shared by ``torchskin detect`` and
``torchskin calibrate``; ``onboard.write_mask``, the writers a streamed frame's mask goes through too)."""

from __future__ import annotations

import os

import numpy as np

from ..onboard import load_cube, write_mask


def write_mask_png(path: str | os.PathLike, mask: np.ndarray) -> None:
    """A greyscale PNG of a boolean (H, W) mask (skin white), written atomically (``onboard.write_mask``)."""
    if not str(path).lower().endswith(".png"):
        raise ValueError(f"--out {str(path)!r} must be a .png mask")
    write_mask(path, mask)


__all__ = ["load_cube", "write_mask_png"]
