"""What every cube format shares (numpy only): the formats' suffixes, wavelength units, ``CubeFile`` (one
frame's cube in a file, read rows by rows), releasing a mapped file's pages and the optional ``formats`` extra."""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io import (
    StrPath,
    as_float32,
)

#: the suffixes of each format (``cube_format``)
ENVI_SUFFIXES = (".hdr",)
TIFF_SUFFIXES = (".tif", ".tiff")
NPY_SUFFIXES = (".npy",)
CUBE_SUFFIXES = NPY_SUFFIXES + ENVI_SUFFIXES + TIFF_SUFFIXES + (".img", ".dat", ".raw", ".bsq", ".bil", ".bip")
#: where Spectral Python looks for an ENVI header's data file (the header's name without ``.hdr``, plus these)
ENVI_DATA_SUFFIXES = ("", ".img", ".dat", ".raw", ".bsq", ".bil", ".bip", ".sli")
#: the GeoTIFF georeferencing tags kept from an input for its outputs: ModelPixelScale, ModelTiepoint,
#: ModelTransformation, GeoKeyDirectory, GeoDoubleParams, GeoAsciiParams
GEOTIFF_TAGS = (33550, 33922, 34264, 34735, 34736, 34737)
GDAL_METADATA_TAG = 42112
#: wavelength units a header may declare -> nm per unit (lower case, spaces and dots removed, "metre" read as
#: "meter")
WAVELENGTH_UNITS = {"nanometers": 1.0, "nanometer": 1.0, "nm": 1.0, "micrometers": 1000.0,
                    "micrometer": 1000.0, "microns": 1000.0,
                    "micron": 1000.0, "um": 1000.0, "µm": 1000.0, "μm": 1000.0, "millimeters": 1e6, "millimeter": 1e6,
                    "mm": 1e6}
#: wavelengths given without units must reach this (nm): all below it they read as micrometres (0.4-2.5 um
#: imagers, 8-14 um thermal ones), which no camera's nanometre centres are (the far ultraviolet)
UNITLESS_MIN_NM = 100.0
FORMAT_HINT = "pip install 'torchskin[formats]'"
#: the units written with each quantity's values (ENVI ``data units``, GDAL's per-band ``UNITTYPE``): reflectance
#: is a factor (1 = a white Lambertian panel), the signal digital numbers
QUANTITY_UNITS = {"reflectance": "1", "signal": "DN"}
#: the formats a cube is written in (``render --format``; ``calibrate`` follows its input)
WRITE_FORMATS = ("npy", "envi", "tiff")


def _need(module: str, what: str) -> Any:
    """Import the optional ``module`` (the ``formats`` extra), or the ``ModuleNotFoundError`` of its top-level
    package, saying what needed it (``what``), that the command line answers with ``errors.missing_extra``'s
    one line and status 1, as for every other missing package."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.partition(".")[0]
        raise ModuleNotFoundError(f"{what} needs the Python package {top!r}: {FORMAT_HINT}", name=top) from None


def cube_format(path: StrPath) -> str:
    """``"npy"``, ``"envi"`` or ``"tiff"`` from a file name (an ENVI data file with a ``.hdr`` beside it is ENVI).

    >>> cube_format("a/reflectance.hdr"), cube_format("scene.TIF"), cube_format("x.npy")
    ('envi', 'tiff', 'npy')
    """
    suf = Path(path).suffix.lower()
    if suf in NPY_SUFFIXES:
        return "npy"
    if suf in TIFF_SUFFIXES:
        return "tiff"
    return "envi"


def units_scale(units: str | None, where: str) -> float | None:
    """nm per unit of a declared wavelength unit (None when none is declared or ENVI's "Unknown");
    ``ValueError`` naming ``where`` for a unit that is not a length (wavenumber, index)."""
    if units is None:
        return None
    key = re.sub(r"[\s.]", "", str(units)).lower().replace("metre", "meter")  # British spellings
    if key in ("", "unknown"):
        return None
    if key not in WAVELENGTH_UNITS:
        raise ValueError(f"{where} declares wavelength units {units!r}; expected nanometers or micrometers")
    return WAVELENGTH_UNITS[key]


def to_nm(values: Sequence[float], units: str | None, where: str) -> list[float]:
    """Band centres in nm from header values in ``units``: declared micrometres are converted; without a unit the
    values must already read as nm (centres all below ``UNITLESS_MIN_NM`` look like micrometres and are refused, as
    an unlabelled unit cannot be guessed); distinct, positive, finite."""
    scale = units_scale(units, where)
    v = [float(x) * (scale or 1.0) for x in values]
    if not all(math.isfinite(x) and x > 0 for x in v):
        raise ValueError(f"{where}: wavelengths must be positive finite numbers")
    if scale is None and max(v) < UNITLESS_MIN_NM:
        raise ValueError(f"{where}: wavelengths {', '.join(f'{x:g}' for x in v[:4])}{', ...' if len(v) > 4 else ''} "
                         "look like micrometres but no units are declared; declare 'wavelength units = "
                         "Micrometers' (or give them in nm)")
    if len(set(v)) != len(v):
        raise ValueError(f"{where}: a wavelength is given twice")
    return v


class CubeFile:
    """One frame's cube in a file: ``bands`` (nm), ``fwhm`` (nm or None), ``shape`` (bands, H, W), ``dtype`` (the
    file's), ``format`` ("npy", "envi", "tiff"), ``geotags`` (a GeoTIFF's georeferencing tags, ``[(code, dtype,
    count, value)]``; empty otherwise), ``envi_map`` (an ENVI header's ``map info`` and ``coordinate system
    string``), ``streaming`` (False when the file is read whole: a compressed GeoTIFF) and ``read_rows``."""

    def __init__(self, path: Path, fmt: str, data: np.ndarray, axes: str, bands: list[float] | None,
                 fwhm: list[float] | None, option: str, geotags: list | None = None,
                 envi_map: dict | None = None, streaming: bool = True, scale: Sequence[float] | None = None,
                 offset: Sequence[float] | None = None):
        self.path, self.format, self.option = path, fmt, option
        self._data, self._axes = data, axes  # axes: the data's layout, "byx" (bsq), "ybx" (bil) or "yxb" (bip)
        n_b = data.shape[axes.index("b")]
        self.shape = (n_b, data.shape[axes.index("y")], data.shape[axes.index("x")])
        self.dtype = data.dtype
        self.bands, self.fwhm = bands, fwhm
        self.geotags = geotags or []
        self.envi_map = envi_map or {}
        self.streaming = streaming
        if bands is not None and len(bands) != n_b:
            raise ValueError(f"{option} {str(path)!r} holds {n_b} bands but its wavelengths list {len(bands)}")
        if fwhm is not None and len(fwhm) != n_b:
            raise ValueError(f"{option} {str(path)!r} holds {n_b} bands but its fwhm lists {len(fwhm)}")
        if fwhm is not None and not all(math.isfinite(f) and f >= 0 for f in fwhm):
            raise ValueError(f"{option} {str(path)!r}: its bands' fwhm must be finite and not negative (nm), got "
                             f"{', '.join(f'{f:g}' for f in fwhm[:6])}{', ...' if len(fwhm) > 6 else ''}")
        # stored values -> the quantity: value * scale + offset per band (ENVI 'reflectance scale factor', GDAL's
        # per-band SCALE and OFFSET: an int16 reflectance product stores 10000 x the factor)
        self.scale = None if scale is None else np.asarray(scale, np.float64).reshape(-1)
        self.offset = None if offset is None else np.asarray(offset, np.float64).reshape(-1)
        for name, v in (("scale", self.scale), ("offset", self.offset)):
            if v is not None and (v.size != n_b or not np.all(np.isfinite(v)) or (name == "scale" and np.any(v == 0))):
                raise ValueError(f"{option} {str(path)!r}: its {name} must be {n_b} finite numbers"
                                 + (" other than 0" if name == "scale" else ""))

    def __repr__(self) -> str:
        return f"CubeFile({str(self.path)!r}, {self.format}, shape={self.shape}, dtype={self.dtype})"

    def read_rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` as native float32 (bands, r1 - r0, W), a copy, reading only those rows from the file;
        the file's pages are then released from the process (``_release``): resident memory stays the tile's."""
        d = self._data
        if self._axes == "byx":
            block = d[:, r0:r1, :]
        elif self._axes == "ybx":
            block = np.transpose(d[r0:r1], (1, 0, 2))
        else:
            block = np.transpose(d[r0:r1], (2, 0, 1))
        try:
            out = as_float32(block)
            out = np.array(out, order="C") if np.shares_memory(out, d) else np.ascontiguousarray(out)
        except ValueError as e:
            raise ValueError(f"{self.option} {str(self.path)!r} {e}") from None
        release_pages(d)
        if self.scale is not None:
            out *= self.scale.astype(np.float32)[:, None, None]
        if self.offset is not None:
            out += self.offset.astype(np.float32)[:, None, None]
        return out

    def read(self) -> np.ndarray:
        """The whole cube, float32 (bands, H, W) (for small cubes and tests)."""
        return self.read_rows(0, self.shape[1])


def _mapping(a: Any) -> Any:
    """The ``mmap.mmap`` under a memory-mapped array or a view of one (None for an array in memory)."""
    import mmap

    x = a
    for _ in range(16):  # views of views: a short chain
        if isinstance(x, mmap.mmap):
            return x
        m = getattr(x, "_mmap", None)
        if isinstance(m, mmap.mmap):
            return m
        x = getattr(x, "base", None)
        if x is None:
            return None
    return None


def release_pages(a: Any) -> None:
    """Drop the pages of the file mapped under array ``a`` from this process (``MADV_DONTNEED``; nothing for an
    array in memory). The page cache keeps them, and a shared mapping's written pages are still written back,
    so nothing is lost: a memory-mapped frame read or written tile by tile would otherwise stay resident,
    counted against the process, as it is streamed (6.4 GB for a 4 x 20000 x 20000 float32 frame)."""
    import mmap

    m = _mapping(a)
    if m is not None and hasattr(mmap, "MADV_DONTNEED"):
        with contextlib.suppress(OSError, ValueError):
            m.madvise(mmap.MADV_DONTNEED)


def iter_row_tiles(H: int, tile_rows: int) -> Iterator[tuple[int, int]]:
    """(r0, r1) row ranges of ``tile_rows`` rows covering ``0..H``."""
    for r0 in range(0, H, tile_rows):
        yield r0, min(r0 + tile_rows, H)


class MappedOutput:
    """A file written through a memory map ``_mm`` inside an atomic-write context ``_ctx`` (a temporary name,
    renamed on success): ``abort`` drops the map and removes the temporary file, leaving the target as it was."""

    _mm: Any
    _ctx: Any

    def abort(self, exc: BaseException | None = None) -> None:
        """Remove the temporary file (the target stays as it was)."""
        with contextlib.suppress(AttributeError):
            del self._mm
        e = exc or RuntimeError("aborted")
        with contextlib.suppress(BaseException):
            self._ctx.__exit__(type(e), e, e.__traceback__)
