"""Cube files in and out, numpy only (no torch): the formats the field's cameras write and its tools open.

Reading (``open_cube``): a cube of one frame, bands x rows x columns, with its wavelengths, from

- ``.npy`` with the wavelength sidecar ``CUBE.bands.json`` (``io.read_bands_sidecar``), memory-mapped;
- ENVI: a ``.hdr`` header over a raw file (``CUBE.hdr`` + ``CUBE``, ``CUBE.img``, ``CUBE.dat``, ``CUBE.raw``,
  ...), opened through Spectral Python (``spectral.envi.open``) and memory-mapped: header ``wavelength``,
  ``wavelength units`` (nanometres; micrometres converted), ``fwhm``, ``interleave`` bsq/bil/bip, ``data type``,
  ``byte order`` and ``header offset``;
- multi-band GeoTIFF through tifffile: each band's wavelength from the GDAL_METADATA tag (the per-band items
  ``wavelength``, ``wavelength_units`` and ``fwhm`` that GDAL's ENVI driver and ``gdal_translate`` write, or GDAL's
  IMAGERY domain ``CENTRAL_WAVELENGTH_UM`` / ``FWHM_UM``), the georeferencing tags (``GEOTIFF_TAGS``) kept for the
  outputs. tifffile rather than rasterio: rasterio needs GDAL's binary wheels (tens of MB, and none for some
  platforms an onboard computer runs), while tifffile is pure Python over numpy, reads the tags byte for byte,
  and memory-maps uncompressed files: what streaming needs. A compressed GeoTIFF cannot be memory-mapped and
  is read whole, within ``--max-megapixels``.

``CubeFile.read_rows(r0, r1)`` reads only rows ``r0:r1`` (float32, bands x rows x W): ``onboard.detect_file`` and
``onboard.calibrate_file`` stream a frame larger than memory through it.

Writing (``CubeWriter``): ``.npy`` + sidecar, ENVI (``.hdr`` with ``wavelength units = Nanometers``,
``wavelength = {...}``, ``fwhm = {...}``, over a BSQ little-endian float32 ``.img``) or GeoTIFF (one page,
planar, float32, GDAL_METADATA per-band items, the input's geotags), tile by tile to temporary files that are
renamed on success (``io.atomic_path``); a mask as GeoTIFF (``write_mask_tiff``) or PNG (``PngRows``).

Spectral Python and tifffile are the ``formats`` extra: without them an ENVI or GeoTIFF file gets one line,
``pip install 'torchskin[formats]'``.
"""

from __future__ import annotations

import contextlib
import math
import re
import struct
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from .io import (
    MAX_MEGAPIXELS,
    StrPath,
    as_float32,
    atomic_path,
    bands_sidecar_text,
    npy_header,
    read_bands_sidecar,
    sidecar_path,
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


def open_cube(path: StrPath, option: str = "--cube", max_megapixels: float = MAX_MEGAPIXELS,
              need_wavelengths: bool = True) -> CubeFile:
    """The cube in ``path`` (``.npy`` + sidecar, ENVI ``.hdr`` or its data file, GeoTIFF) with its wavelengths,
    memory-mapped; every problem a one-line ``ValueError`` naming ``option`` and the file. ``max_megapixels``
    caps only a cube that must be read whole (a compressed GeoTIFF). An ENVI or GeoTIFF cube without
    wavelengths is refused unless ``need_wavelengths`` is False (``detect --bands`` gives them); a ``.npy``
    without its sidecar is read as it is (``bands`` None)."""
    from .errors import check_input_file

    p = check_input_file(path, option, CUBE_SUFFIXES)
    fmt = cube_format(p)
    if fmt == "npy":
        return _open_npy(p, option)
    if fmt == "envi":
        return _open_envi(p, option, need_wavelengths)
    return _open_tiff(p, option, max_megapixels, need_wavelengths)


def open_npy(p: Path, option: str, one_frame: bool = True, max_megapixels: float | None = None) -> np.ndarray:
    """The data of a ``.npy`` cube, memory-mapped (no pickles), after the checks of its header, before any data
    is read or mapped: the one ``.npy`` reader of the onboard commands (``open_cube``'s one frame,
    ``onboard.load_cube``'s frames). Refused, each a one-line ``ValueError`` naming ``option`` and the file: a
    header that does not parse, other values than real numbers, with ``one_frame`` any other shape than (bands,
    H, W) of non-zero sizes (else no values at all), frames above ``max_megapixels`` (H x W, when given), and a
    file shorter than its header's cube (a copy cut short, a disk that filled)."""
    from .errors import one_line

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
    from .errors import one_line

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


def _gdal_items(xml: str) -> tuple[dict[str, str], dict[int, dict[str, str]]]:
    """GDAL_METADATA's items: (dataset-level {name: value}, {band index: {name: value}}), names lower case."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml.strip().strip("\x00"))
    top: dict[str, str] = {}
    per: dict[int, dict[str, str]] = {}
    for item in root.iter("Item"):
        name = (item.get("name") or "").lower()
        text = (item.text or "").strip()
        if item.get("sample") is None:
            top[name] = text
        else:
            per.setdefault(int(item.get("sample") or 0), {})[name] = text
    return top, per


def _tiff_scale_offset(xml: str | None, nb: int, where: str) -> tuple[list[float] | None, list[float] | None]:
    """GDAL_METADATA's per-band ``SCALE`` and ``OFFSET`` (value = stored x SCALE + OFFSET); None when no band gives
    one (a band without one: 1 and 0)."""
    if not xml:
        return None, None
    with contextlib.suppress(Exception):  # a malformed tag is refused by _tiff_wavelengths
        _, per = _gdal_items(xml)
        out: list[list[float] | None] = []
        for name, default in (("scale", 1.0), ("offset", 0.0)):
            if not any(name in per.get(b, {}) for b in range(nb)):
                out.append(None)
                continue
            try:
                out.append([float(per.get(b, {}).get(name, default)) for b in range(nb)])
            except ValueError:
                raise ValueError(f"{where}: a band's {name.upper()} in GDAL_METADATA is not a number") from None
        return out[0], out[1]
    return None, None


def _tiff_wavelengths(xml: str | None, nb: int, where: str) -> tuple[list[float] | None, list[float] | None]:
    """Band centres and FWHM (nm) from a GDAL_METADATA tag; (None, None) when it gives none."""
    if not xml:
        return None, None
    try:
        top, per = _gdal_items(xml)
    except Exception:  # noqa: BLE001 - malformed XML: as if there were no metadata
        raise ValueError(f"{where}: its GDAL_METADATA tag is not valid XML") from None
    centres, fwhm = [], []
    for b in range(nb):
        d = per.get(b, {})
        try:
            if "wavelength" in d:
                s = units_scale(d.get("wavelength_units", top.get("wavelength_units")), where)
                centres.append((float(d["wavelength"]), s))
                fwhm.append(float(d["fwhm"]) * (s or 1.0) if "fwhm" in d else None)
            elif "central_wavelength_um" in d:
                centres.append((float(d["central_wavelength_um"]), 1000.0))
                fwhm.append(float(d["fwhm_um"]) * 1000.0 if "fwhm_um" in d else None)
            else:
                return None, None
        except ValueError:
            raise ValueError(f"{where}: band {b + 1}'s wavelength in GDAL_METADATA is not a number") from None
    scales = {s for _, s in centres}
    if None in scales and len(scales) > 1:
        raise ValueError(f"{where}: some bands declare their wavelength units and others do not")
    if None in scales:
        bands = to_nm([c for c, _ in centres], None, where)
    else:  # each band in its declared unit (bands may declare different ones)
        bands = to_nm([c * (s or 1.0) for c, s in centres], "nm", where)
    return bands, (None if any(f is None for f in fwhm) else [float(f) for f in fwhm if f is not None])


def _open_tiff(p: Path, option: str, max_megapixels: float, need_wavelengths: bool = True) -> CubeFile:
    from .errors import one_line

    tifffile = _need("tifffile", f"{option} {str(p)!r} (GeoTIFF)")
    where = f"{option} {str(p)!r}"
    try:
        with tifffile.TiffFile(str(p)) as tif:
            page = tif.pages[0]
            series = tif.series[0]
            axes, shape, dtype = series.axes, tuple(series.shape), np.dtype(series.dtype)
            xml = page.tags[GDAL_METADATA_TAG].value if GDAL_METADATA_TAG in page.tags else None
            geotags = [(c, int(page.tags[c].dtype), page.tags[c].count, page.tags[c].value)
                       for c in GEOTIFF_TAGS if c in page.tags]
            compressed = int(page.compression) != 1
    except Exception as e:  # noqa: BLE001 - tifffile raises its own types for a bad file
        raise ValueError(f"cannot read {where}: {one_line(e)}") from None
    if dtype.kind not in "fiu":
        raise ValueError(f"{where} must hold real numbers, got dtype {dtype}")
    if len(shape) == 2:
        axes, shape = "S" + axes, (1, *shape)
    if len(shape) != 3 or axes[-2:] not in ("YX", "XS") and axes[1:] != "YX":
        raise ValueError(f"{where}: expected one multi-band image (bands, rows, columns), got axes {axes!r} "
                         f"shape {shape}")
    lay = "yxb" if axes.endswith("S") and axes[0] == "Y" else "byx"
    nb = shape[lay.index("b")]
    bands, fwhm = _tiff_wavelengths(xml, nb, where)
    scale, offset = _tiff_scale_offset(xml, nb, where)
    if bands is None and need_wavelengths:
        raise ValueError(f"{where} gives no band wavelengths: expected GDAL_METADATA items 'wavelength' (and "
                         "'wavelength_units') for every band")
    data = None
    streaming = not compressed
    if streaming:
        try:
            data = tifffile.memmap(str(p), mode="r")
        except Exception:  # noqa: BLE001 - not memory-mappable (tiles, strips apart): read whole
            streaming = False
    if data is None:
        mp = shape[lay.index("y")] * shape[lay.index("x")] / 1e6
        if mp > max_megapixels:
            raise ValueError(f"{where} is compressed (read whole, not streamed) and its frames are {mp:.1f} "
                             f"megapixels, above the cap of {max_megapixels:g} (--max-megapixels raises it; or "
                             "write it uncompressed)")
        try:
            data = tifffile.imread(str(p))
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"cannot read {where}: {one_line(e)}") from None
    data = np.asarray(data).reshape(shape)
    return CubeFile(p, "tiff", data, lay, bands, fwhm, option, geotags=geotags, streaming=streaming, scale=scale,
                    offset=offset)


# --------------------------------------------------------------------------------------------------- writing
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


def gdal_metadata_xml(bands: Sequence[float] | None, fwhm: Sequence[float] | None,
                      quantity: str | None = None, units: str | None = None) -> str | None:
    """The GDAL_METADATA tag text with each band's ``wavelength``, ``wavelength_units`` (nm) and ``fwhm`` items,
    as GDAL's ENVI driver writes them, and the values' ``units`` as each band's unit type (None without
    wavelengths)."""
    if bands is None:
        return None
    items = [] if quantity is None else [f'<Item name="quantity">{escape(quantity)}</Item>']
    if units is not None:
        items.append(f'<Item name="units">{escape(units)}</Item>')
    for i, b in enumerate(bands):
        items.append(f'<Item name="DESCRIPTION" sample="{i}" role="description">{b:g} nm</Item>')
        if units is not None:
            items.append(f'<Item name="UNITTYPE" sample="{i}" role="unittype">{escape(units)}</Item>')
        items.append(f'<Item name="wavelength" sample="{i}">{b:g}</Item>')
        items.append(f'<Item name="wavelength_units" sample="{i}">Nanometers</Item>')
        if fwhm is not None:
            items.append(f'<Item name="fwhm" sample="{i}">{fwhm[i]:g}</Item>')
    return "<GDALMetadata>" + "".join(items) + "</GDALMetadata>"


def tiff_extratags(bands: Sequence[float] | None, fwhm: Sequence[float] | None, geotags: Sequence = (),
                   quantity: str | None = None) -> list:
    """tifffile ``extratags``: the input's geotags and the GDAL_METADATA wavelengths (and ``quantity``'s units,
    ``QUANTITY_UNITS``)."""
    tags = [(c, dt, n, v, True) for c, dt, n, v in geotags]
    xml = gdal_metadata_xml(bands, fwhm, quantity, QUANTITY_UNITS.get(quantity or ""))
    if xml is not None:
        tags.append((GDAL_METADATA_TAG, 2, 0, xml, True))
    return tags


class CubeWriter:
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

    def abort(self, exc: BaseException | None = None) -> None:
        """Remove the temporary file (the target stays as it was)."""
        with contextlib.suppress(AttributeError):
            del self._mm
        e = exc or RuntimeError("aborted")
        with contextlib.suppress(BaseException):
            self._ctx.__exit__(type(e), e, e.__traceback__)

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


# ------------------------------------------------------------------------------------------------------ masks
class PngRows:
    """A greyscale 8-bit PNG of ``H`` x ``W`` written rows by rows (``write_rows`` of uint8 (rows, W), in order)
    through one zlib stream into a temporary file, renamed on ``close()``: no whole image in memory."""

    def __init__(self, path: StrPath, H: int, W: int):
        self.H, self.W, self.rows = int(H), int(W), 0
        self._ctx = atomic_path(path)
        self._tmp = self._ctx.__enter__()
        self._fh = open(self._tmp, "wb")  # noqa: SIM115 - closed by close()/abort()
        self._z = zlib.compressobj(6)
        self._fh.write(b"\x89PNG\r\n\x1a\n" + self._chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0)))

    @staticmethod
    def _chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    def write_rows(self, rows: np.ndarray) -> None:
        a = np.ascontiguousarray(rows, dtype=np.uint8)
        raw = np.concatenate([np.zeros((a.shape[0], 1), np.uint8), a], 1).tobytes()  # filter 0 before each row
        data = self._z.compress(raw)
        if data:
            self._fh.write(self._chunk(b"IDAT", data))
        self.rows += a.shape[0]

    def close(self) -> None:
        if self.rows != self.H:
            raise RuntimeError(f"PNG got {self.rows} rows of {self.H}")
        self._fh.write(self._chunk(b"IDAT", self._z.flush()) + self._chunk(b"IEND", b""))
        self._fh.close()
        self._ctx.__exit__(None, None, None)

    def abort(self, exc: BaseException | None = None) -> None:
        self._fh.close()
        e = exc or RuntimeError("aborted")
        with contextlib.suppress(BaseException):
            self._ctx.__exit__(type(e), e, e.__traceback__)


class TiffMaskRows:
    """A uint8 (H, W) mask GeoTIFF (skin 255) with ``geotags``, written rows by rows into a memory-mapped
    temporary file, renamed on ``close()``."""

    def __init__(self, path: StrPath, H: int, W: int, geotags: Sequence = ()):
        tifffile = _need("tifffile", f"writing {str(path)!r} (GeoTIFF)")
        self.H = int(H)
        self._ctx = atomic_path(path)
        tmp = self._ctx.__enter__()
        try:
            self._mm = tifffile.memmap(str(tmp), shape=(H, W), dtype=np.uint8, photometric="minisblack",
                                       extratags=tiff_extratags(None, None, geotags))
        except BaseException as e:
            self._ctx.__exit__(type(e), e, e.__traceback__)
            raise
        self.rows = 0

    def write_rows(self, rows: np.ndarray) -> None:
        self._mm[self.rows:self.rows + rows.shape[0]] = rows
        self.rows += rows.shape[0]
        release_pages(self._mm)

    def close(self) -> None:
        self._mm.flush()
        del self._mm
        self._ctx.__exit__(None, None, None)

    def abort(self, exc: BaseException | None = None) -> None:
        with contextlib.suppress(AttributeError):
            del self._mm
        e = exc or RuntimeError("aborted")
        with contextlib.suppress(BaseException):
            self._ctx.__exit__(type(e), e, e.__traceback__)


def read_png_gray(path: StrPath) -> np.ndarray:
    """An 8-bit greyscale PNG written by ``PngRows`` or ``io.write_png`` as a uint8 (H, W) array (for tests and
    comparisons; filter type 0 only)."""
    data = Path(path).read_bytes()
    pos, idat, w, h = 8, [], 0, 0
    while pos < len(data):
        n, tag = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if tag == b"IHDR":
            w, h = struct.unpack(">II", body[:8])
        elif tag == b"IDAT":
            idat.append(body)
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, w + 1)
    return raw[:, 1:]


def iter_row_tiles(H: int, tile_rows: int) -> Iterator[tuple[int, int]]:
    """(r0, r1) row ranges of ``tile_rows`` rows covering ``0..H``."""
    for r0 in range(0, H, tile_rows):
        yield r0, min(r0 + tile_rows, H)


__all__ = ["CubeFile", "CubeWriter", "PngRows", "TiffMaskRows", "cube_format", "envi_header_text", "envi_paths",
           "gdal_metadata_xml", "iter_row_tiles", "open_cube", "output_path", "read_png_gray", "release_pages", "to_nm",
           "write_cube"]
