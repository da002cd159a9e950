"""ENVI cubes: a ``.hdr`` header over a raw data file, read through Spectral Python (``_open_envi``), and the
header written with a cube (``envi_header_text``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io import (
    StrPath,
)
from .common import ENVI_DATA_SUFFIXES, CubeFile, _need, to_nm, units_scale


def envi_paths(path: StrPath) -> tuple[Path, Path | None]:
    """(header, data file) of an ENVI cube named by either; the data file None when none is found."""
    p = Path(path)
    if p.suffix.lower() == ".hdr":
        hdr = p
        stem = p.with_suffix("")
        for s in ENVI_DATA_SUFFIXES:
            cand = Path(str(stem) + s)
            if cand.is_file() and cand != hdr:
                return hdr, cand
        return hdr, None
    for hdr in (Path(str(p) + ".hdr"), p.with_suffix(".hdr")):
        if hdr.is_file():
            return hdr, p
    return p.with_suffix(".hdr"), p


_ENVI_DTYPES = {1: "u1", 2: "i2", 3: "i4", 4: "f4", 5: "f8", 12: "u2", 13: "u4", 14: "i8", 15: "u8"}


def _open_envi(p: Path, option: str, need_wavelengths: bool = True) -> CubeFile:
    from ..errors import one_line

    hdr, raw = envi_paths(p)
    if not hdr.is_file():
        raise ValueError(f"{option} {str(p)!r}: no ENVI header {str(hdr)!r} beside it")
    if raw is None:
        raise ValueError(f"{option} {str(hdr)!r}: no data file beside the header (looked for "
                         f"{', '.join(repr(str(hdr.with_suffix(s))) for s in ENVI_DATA_SUFFIXES if s)})")
    envi = _need("spectral.io.envi", f"{option} {str(hdr)!r} (ENVI)")
    try:
        meta = envi.read_envi_header(str(hdr))
    except Exception as e:  # noqa: BLE001 - spectral raises its own types for a bad header
        raise ValueError(f"cannot read the ENVI header {option} {str(hdr)!r}: {one_line(e)}") from None
    where = f"{option} {str(hdr)!r}"
    try:
        lines, samples, nb = int(meta["lines"]), int(meta["samples"]), int(meta["bands"])
        dt = int(meta.get("data type", 0))
        offset = int(meta.get("header offset", 0))
        order = int(meta.get("byte order", 0))
    except (KeyError, ValueError) as e:
        raise ValueError(f"{where}: the header needs integer 'lines', 'samples', 'bands' and 'data type' "
                         f"({one_line(e)})") from None
    if dt not in _ENVI_DTYPES:
        raise ValueError(f"{where}: data type {dt} is not a real number type (expected one of "
                         f"{sorted(_ENVI_DTYPES)})")
    interleave = str(meta.get("interleave", "bsq")).strip().lower()
    if interleave not in ("bsq", "bil", "bip"):
        raise ValueError(f"{where}: interleave {interleave!r}; expected bsq, bil or bip")
    if min(lines, samples, nb) < 1 or order not in (0, 1):
        raise ValueError(f"{where}: lines, samples and bands must be >= 1 and byte order 0 or 1")
    dtype = np.dtype(_ENVI_DTYPES[dt]).newbyteorder(">" if order else "<")
    need = offset + lines * samples * nb * dtype.itemsize
    size = raw.stat().st_size
    if size != need:
        what = "truncated" if size < need else "larger than the header says"
        raise ValueError(f"{where}: the data file {str(raw)!r} is {what}: {size} bytes, but {interleave} "
                         f"{nb} bands x {lines} lines x {samples} samples of {dtype.itemsize}-byte "
                         f"{dtype.name} after a {offset}-byte offset need {need}")
    if "wavelength" not in meta and need_wavelengths:
        raise ValueError(f"{where} gives no 'wavelength' list: the bands' centres are needed (detect picks the "
                         "model's bands by them, calibrate writes them with its cube): add 'wavelength = {...}' and "
                         "'wavelength units' to the header (detect: or give --bands)")
    try:
        wl = [float(v) for v in meta["wavelength"]] if "wavelength" in meta else None
        fw = [float(v) for v in meta["fwhm"]] if "fwhm" in meta and wl is not None else None
        rsf = float(meta["reflectance scale factor"]) if "reflectance scale factor" in meta else None
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: 'wavelength', 'fwhm' and 'reflectance scale factor' must be numbers "
                         f"({one_line(e)})") from None
    if rsf is not None and not (math.isfinite(rsf) and rsf > 0):
        raise ValueError(f"{where}: 'reflectance scale factor' must be a positive number, got {rsf:g}")
    units = meta.get("wavelength units")
    bands = None if wl is None else to_nm(wl, units, where)
    unit_nm = units_scale(units, where) or 1.0
    fwhm = None if fw is None else [v * unit_nm for v in fw]
    try:
        img = envi.open(str(hdr), str(raw))
        data = img.open_memmap(interleave="source", writable=False)  # the file's own interleave: no copy
    except Exception as e:  # noqa: BLE001 - spectral raises its own types
        raise ValueError(f"cannot read {where}: {one_line(e)}") from None
    axes = {"bsq": "byx", "bil": "ybx", "bip": "yxb"}[interleave]
    envi_map = {k: meta[k] for k in ("map info", "coordinate system string") if k in meta}
    # ENVI's 'reflectance scale factor': the stored value of a reflectance of 1 (10000 for int16 products)
    scale = None if rsf is None or rsf == 1 else [1.0 / rsf] * nb
    return CubeFile(raw, "envi", data, axes, bands, fwhm, option, envi_map=envi_map, scale=scale)


def envi_header_text(shape: tuple[int, int, int], bands: Sequence[float] | None, fwhm: Sequence[float] | None,
                     description: str = "torchskin", extra: dict | None = None, units: str | None = None,
                     reflectance: bool = False, dtype: Any = np.float32) -> str:
    """An ENVI header for a BSQ, little-endian ``dtype`` (float32) cube of ``shape`` (bands, H, W), wavelengths and FWHM in
    nm; ``units``: the values' (``data units``); ``reflectance``: a 0-1 reflectance factor (``reflectance scale
    factor = 1``)."""
    nb, h, w = shape
    code = {np.dtype(v): k for k, v in _ENVI_DTYPES.items()}[np.dtype(dtype)]
    lines = ["ENVI", f"description = {{{description}}}", f"samples = {w}", f"lines = {h}", f"bands = {nb}",
             "header offset = 0", "file type = ENVI Standard", f"data type = {code}", "interleave = bsq",
             "byte order = 0"]
    if units is not None:
        lines.append(f"data units = {units}")
    if reflectance:
        lines.append("reflectance scale factor = 1")
    if bands is not None:
        lines += ["wavelength units = Nanometers", "wavelength = {" + ", ".join(f"{b:g}" for b in bands) + "}"]
        lines.append("band names = {" + ", ".join(f"{b:g} nm" for b in bands) + "}")
    if fwhm is not None:
        lines.append("fwhm = {" + ", ".join(f"{f:g}" for f in fwhm) + "}")
    for k, v in (extra or {}).items():
        val = "{" + ", ".join(str(x) for x in v) + "}" if isinstance(v, (list, tuple)) else f"{{{v}}}"
        lines.append(f"{k} = {val}")
    return "\n".join(lines) + "\n"
