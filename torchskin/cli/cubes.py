"""The onboard commands' file handling, numpy only: a checked ``.npy`` cube in, a mask PNG out (shared by
``torchskin detect`` and ``torchskin calibrate``)."""

from __future__ import annotations

import os

import numpy as np

from ..errors import check_input_file, one_line
from ..io import write_png


def load_cube(path: str | os.PathLike, option: str = "--cube") -> np.ndarray:
    """A numeric, non-empty, finite array from a ``.npy`` file (no pickles, no ``.npz`` archives), with a
    one-line ``ValueError`` naming ``option`` and the file otherwise."""
    p = check_input_file(path, option, (".npy",))
    try:
        x = np.load(p, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"cannot read {option} {str(p)!r}: {one_line(e)}") from None
    if not isinstance(x, np.ndarray):
        raise ValueError(f"{option} {str(p)!r} is not a single .npy array")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise ValueError(f"{option} {str(p)!r} must hold numbers, got dtype {x.dtype}")
    if x.size == 0:
        raise ValueError(f"{option} {str(p)!r} is empty (shape {x.shape})")
    if np.issubdtype(x.dtype, np.floating) and not np.isfinite(x).all():
        raise ValueError(f"{option} {str(p)!r} holds NaN or infinite values")
    return x


def write_mask_png(path: str | os.PathLike, mask: np.ndarray) -> None:
    """A greyscale PNG of a boolean (H, W) mask (skin white), written atomically (``io.write_png``)."""
    write_png(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)



__all__ = ["load_cube", "write_mask_png"]
