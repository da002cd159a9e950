"""A cube file in any format: ``open_cube`` opens one by its name (``cube_format``), ``CubeWriter`` and
``write_cube`` write one tile by tile to temporary files renamed on success."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io import (
    MAX_MEGAPIXELS,
    StrPath,
    atomic_path,
    bands_sidecar_text,
    sidecar_path,
)
from .common import (
    CUBE_SUFFIXES,
    ENVI_DATA_SUFFIXES,
    QUANTITY_UNITS,
    CubeFile,
    MappedOutput,
    _need,
    cube_format,
    release_pages,
)
from .envi import _open_envi, envi_header_text
from .npy import _open_npy
from .tiff import _open_tiff, tiff_extratags


def open_cube(path: StrPath, option: str = "--cube", max_megapixels: float = MAX_MEGAPIXELS,
              need_wavelengths: bool = True) -> CubeFile:
    """The cube in ``path`` (``.npy`` + sidecar, ENVI ``.hdr`` or its data file, GeoTIFF) with its wavelengths,
    memory-mapped; every problem a one-line ``ValueError`` naming ``option`` and the file. ``max_megapixels``
    caps only a cube that must be read whole (a compressed GeoTIFF). An ENVI or GeoTIFF cube without
    wavelengths is refused unless ``need_wavelengths`` is False (``detect --bands`` gives them); a ``.npy``
    without its sidecar is read as it is (``bands`` None)."""
    from ..errors import check_input_file

    p = check_input_file(path, option, CUBE_SUFFIXES)
    fmt = cube_format(p)
    if fmt == "npy":
        return _open_npy(p, option)
    if fmt == "envi":
        return _open_envi(p, option, need_wavelengths)
    return _open_tiff(p, option, max_megapixels, need_wavelengths)


class CubeWriter(MappedOutput):
    """A float32 (or ``dtype``: ENVI masks are uint8) (bands, H, W) cube written rows by rows (``write_rows``) into a memory-mapped temporary file in
    ``fmt`` ("npy": + the sidecar; "envi": ``.hdr`` + ``.img``; "tiff"), renamed onto ``path`` by ``close()``;
    ``abort()`` (or an exception inside ``with``) removes it and leaves ``path`` as it was."""

    def __init__(self, path: StrPath, shape: tuple[int, int, int], fmt: str, bands: Sequence[float] | None,
                 fwhm: Sequence[float] | None = None, quantity: str = "reflectance", geotags: Sequence = (),
                 envi_extra: dict | None = None, dtype: Any = np.float32):
        self.path, self.format = Path(path), fmt
        self.shape: tuple[int, int, int] = (int(shape[0]), int(shape[1]), int(shape[2]))
        self.bands = None if bands is None else [float(b) for b in bands]
        self.fwhm = None if fwhm is None else [float(f) for f in fwhm]
        self.quantity, self.geotags, self.envi_extra = quantity, list(geotags), envi_extra
        self.dtype = np.dtype(dtype)
        self.data_path = self.path.with_suffix(".img") if fmt == "envi" else self.path
        if fmt == "envi":  # a reader finds the header's data file by name, in ENVI_DATA_SUFFIXES' order
            hdr = self.path.with_suffix(".hdr")
            for suf in ENVI_DATA_SUFFIXES[:ENVI_DATA_SUFFIXES.index(".img")]:
                other = Path(str(hdr.with_suffix("")) + suf)
                if other.is_file() and other != hdr:
                    raise ValueError(f"--out {str(hdr)!r}: {str(other)!r} beside it would be read as its data file "
                                     f"instead of {str(self.data_path)!r} (the one written): remove it or "
                                     "choose another name")
        self._ctx = atomic_path(self.data_path)
        tmp = self._ctx.__enter__()
        try:
            if fmt == "npy":
                self._mm = np.lib.format.open_memmap(tmp, mode="w+", dtype=self.dtype, shape=self.shape)
            elif fmt == "envi":
                self._mm = np.memmap(tmp, dtype=self.dtype.newbyteorder("<"), mode="w+", shape=self.shape)
            elif fmt == "tiff":
                tifffile = _need("tifffile", f"writing {str(self.path)!r} (GeoTIFF)")
                self._mm = tifffile.memmap(str(tmp), shape=self.shape, dtype=np.float32, photometric="minisblack",
                                           planarconfig="separate",
                                           extratags=tiff_extratags(self.bands, self.fwhm, self.geotags, quantity))
            else:
                raise ValueError(f"unknown cube format {fmt!r}; expected npy, envi or tiff")
        except BaseException as e:
            self._ctx.__exit__(type(e), e, e.__traceback__)
            raise

    def write_rows(self, r0: int, block: np.ndarray) -> None:
        """Rows ``r0 .. r0 + len`` of every band: ``block`` (bands, rows, W) (the pages then released from the
        process: ``release_pages``)."""
        self._mm[:, r0:r0 + block.shape[1], :] = block
        release_pages(self._mm)

    def close(self) -> None:
        """Flush; write the header or sidecar to its own temporary file; then rename the data and right after
        it the header onto their names. Any failure before the renames leaves both files as they were; only
        an interruption between the two renames (the header's fsync) can pair new data with an old header."""
        self._mm.flush()
        del self._mm
        side: Path | None = None
        text = ""
        if self.format == "envi":
            side, text = self.path.with_suffix(".hdr"), envi_header_text(
                self.shape, self.bands, self.fwhm, f"torchskin {self.quantity}", self.envi_extra,
                QUANTITY_UNITS.get(self.quantity), self.quantity == "reflectance", self.dtype)
        elif self.format == "npy" and self.bands is not None:
            side, text = sidecar_path(self.path), bands_sidecar_text(self.bands, self.fwhm, self.quantity)
        if side is None:
            self._ctx.__exit__(None, None, None)
            stale = sidecar_path(self.path)
            if self.format == "npy" and stale.is_file():  # an earlier output's wavelengths do not describe this one
                stale.unlink()
            return
        try:
            with atomic_path(side) as tmp_side:
                tmp_side.write_text(text)
                self._ctx.__exit__(None, None, None)  # the data renamed; the header's rename follows at once
        except BaseException as e:
            with contextlib.suppress(BaseException):
                self._ctx.__exit__(type(e), e, e.__traceback__)
            raise

    def __enter__(self) -> CubeWriter:
        return self

    def __exit__(self, et: Any, e: Any, tb: Any) -> None:
        if et is None:
            self.close()
        else:
            self.abort(e)


def output_path(path: StrPath, fmt: str) -> Path:
    """The file a cube in ``fmt`` is written to when named ``path``: an ENVI cube is named by its ``.hdr``."""
    p = Path(path)
    return p.with_suffix(".hdr") if fmt == "envi" and p.suffix.lower() != ".hdr" else p


def write_cube(path: StrPath, cube: np.ndarray, fmt: str, bands: Sequence[float] | None,
               fwhm: Sequence[float] | None = None, quantity: str = "reflectance") -> Path:
    """A whole (bands, H, W) cube in ``fmt`` (``CubeWriter``); returns the path it is named by."""
    p = output_path(path, fmt)
    with CubeWriter(p, cube.shape, fmt, bands, fwhm, quantity) as w:
        w.write_rows(0, np.asarray(cube, dtype=np.float32))
    return p
