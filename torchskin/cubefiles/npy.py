"""``.npy`` cubes: the one ``.npy`` reader of the onboard commands (``open_npy``) and a ``.npy`` cube with its
wavelength sidecar as a ``CubeFile``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..io import (
    npy_header,
    read_bands_sidecar,
    sidecar_path,
)
from .common import CubeFile


def open_npy(p: Path, option: str, one_frame: bool = True, max_megapixels: float | None = None) -> np.ndarray:
    """The data of a ``.npy`` cube, memory-mapped (no pickles), after the checks of its header, before any data
    is read or mapped: the one ``.npy`` reader of the onboard commands (``open_cube``'s one frame,
    ``onboard.load_cube``'s frames). Refused, each a one-line ``ValueError`` naming ``option`` and the file: a
    header that does not parse, other values than real numbers, with ``one_frame`` any other shape than (bands,
    H, W) of non-zero sizes (else no values at all), frames above ``max_megapixels`` (H x W, when given), and a
    file shorter than its header's cube (a copy cut short, a disk that filled)."""
    from ..errors import one_line

    try:
        shape, dtype = npy_header(p)
        with open(p, "rb") as fh:  # the data's offset: the header's end
            v = np.lib.format.read_magic(fh)
            (np.lib.format.read_array_header_1_0 if v == (1, 0) else np.lib.format.read_array_header_2_0)(fh)
            offset = fh.tell()
    except (OSError, ValueError, EOFError, SyntaxError) as e:
        raise ValueError(f"cannot read {option} {str(p)!r}: {one_line(e)}") from None
    if dtype.hasobject or dtype.kind not in "fiu":
        raise ValueError(f"{option} {str(p)!r} must hold numbers, got dtype {dtype}")
    if one_frame and (len(shape) != 3 or 0 in shape):
        raise ValueError(f"{option} {str(p)!r} must be one frame (bands, H, W), got shape {shape}")
    if math.prod(shape) == 0:
        raise ValueError(f"{option} {str(p)!r} is empty (shape {shape})")
    if max_megapixels is not None and len(shape) >= 2:
        mp = shape[-1] * shape[-2] / 1e6
        if mp > max_megapixels:
            raise ValueError(f"{option} {str(p)!r} frames are {shape[-2]} x {shape[-1]} = {mp:.1f} megapixels, above "
                             f"the cap of {max_megapixels:g} (--max-megapixels raises it)")
    need, size = offset + math.prod(shape) * dtype.itemsize, p.stat().st_size
    if size < need:  # checked from the header before anything is mapped: a copy cut short, a disk that filled
        raise ValueError(f"{option} {str(p)!r} is truncated: {size} bytes, but its header's {dtype.name} "
                         f"{' x '.join(map(str, shape))} cube needs {need}")
    try:
        return np.load(p, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"cannot read {option} {str(p)!r}: {one_line(e)}") from None


def _open_npy(p: Path, option: str) -> CubeFile:
    data = open_npy(p, option)
    bands = read_bands_sidecar(p)
    fwhm = None
    if bands is not None:
        import json

        try:  # read_bands_sidecar has read the file as JSON with 'bands_nm'
            f = json.loads(sidecar_path(p).read_text()).get("fwhm_nm")
            fwhm = [float(x) for x in f] if f is not None else None
        except (OSError, ValueError, TypeError):
            raise ValueError(f"the band sidecar {str(sidecar_path(p))!r}: 'fwhm_nm' must be a list of numbers (nm)"
                             ) from None
    return CubeFile(p, "npy", data, "byx", bands, fwhm, option)
