"""Onboard cube files, streamed: a checked ``.npy`` cube read whole (``load_cube``), a frame's detection and
calibration in row tiles (``detect_file``, ``calibrate_file``) and the mask writers (``write_mask``). numpy only."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..io import MAX_MEGAPIXELS, StrPath, as_float32
from .bandplan import apply_plan, band_plan, plan_bands
from .checks import REFLECTANCE_MAX, check_reflectance_range
from .elm import check_panel_regions, elm_apply, elm_line, panel_reference, panel_signal
from .runtime import OnboardDetector  # imported, not under TYPE_CHECKING: the docs resolve detect_file's annotation

#: ``load_cube`` checks a cube for NaN and infinities this many values at a time (bounded temporaries)
_FINITE_CHUNK = 1 << 22


def load_cube(path: StrPath, option: str = "--cube", max_megapixels: float = MAX_MEGAPIXELS) -> np.ndarray:
    """The cube a command reads (``detect``, ``calibrate``): a ``.npy`` file (no pickles, no ``.npz``) of real
    numbers, (bands, H, W) or (frames, bands, H, W), non-empty and finite, returned as native float32
    (``io.as_float32``: float64, float16, big-endian and integer files convert alike). Its frame size (H x W)
    must be at most ``max_megapixels`` (``io.MAX_MEGAPIXELS``, what ``--max-megapixels`` raises), checked from the
    header before any data is read; a native float32 file is memory-mapped rather than read whole. Every
    problem is a one-line ``ValueError`` naming ``option`` and the file: the header's checks are
    ``cubefiles.open_npy``'s (the one ``.npy`` reader: a file shorter than its header's cube is refused as
    truncated), then the values' (finite)."""
    from ..cubefiles import open_npy
    from ..errors import check_input_file

    p = check_input_file(path, option, (".npy",))
    if not (np.isfinite(max_megapixels) and max_megapixels > 0):
        raise ValueError(f"--max-megapixels must be a positive number, got {max_megapixels}")
    x = as_float32(open_npy(p, option, one_frame=False, max_megapixels=max_megapixels))
    flat = x.reshape(-1)
    for lo in range(0, flat.size, _FINITE_CHUNK):  # chunks: no temporary the size of the cube
        if not np.isfinite(flat[lo:lo + _FINITE_CHUNK]).all():
            raise ValueError(f"{option} {str(p)!r} holds NaN or infinite values")
    return x


#: bytes of the input cube's rows per tile of ``detect_file`` and ``calibrate_file`` when ``tile_rows`` is None:
#: the rows per tile are this over bands x W x 4 (at least 1), so that peak memory is a few times this, whatever
#: the frame's height and the cube's band count (a 4-band 20000-column frame: 104 rows; 121 bands: 3 rows)
TILE_BYTES = 32 * 2**20


def _check_tile_rows(tile_rows: int | None, shape: tuple[int, int, int] = (1, 1, 1)) -> int:
    """``tile_rows`` checked, or for None the rows of a ``(bands, H, W)`` cube that fill ``TILE_BYTES``."""
    if tile_rows is None:
        return max(1, TILE_BYTES // (4 * shape[0] * shape[2]))
    if isinstance(tile_rows, bool) or not isinstance(tile_rows, (int, np.integer)) or tile_rows < 1:
        raise ValueError(f"--tile-rows must be a positive whole number of rows, got {tile_rows!r}")
    return int(tile_rows)


class _EnviMaskRows:
    """An ENVI uint8 mask (one band, skin 255) with the input's ``map info`` and ``coordinate system string``,
    written rows by rows (``cubefiles.CubeWriter``)."""

    def __init__(self, out: StrPath, shape: tuple[int, int], envi_map: dict):
        from ..cubefiles import CubeWriter

        self.rows = 0
        self._w = CubeWriter(out, (1, shape[0], shape[1]), "envi", None, quantity="skin mask", envi_extra=envi_map,
                             dtype=np.uint8)

    def write_rows(self, rows: np.ndarray) -> None:
        self._w.write_rows(self.rows, rows[None])
        self.rows += rows.shape[0]

    def close(self) -> None:
        self._w.close()

    def abort(self, exc: BaseException | None = None) -> None:
        self._w.abort(exc)


def _mask_writer(out: StrPath, shape: tuple[int, int], geotags: list, envi_map: dict | None = None) -> Any:
    """The mask's row writer by ``out``'s suffix: ``.png``; ``.tif`` (a GeoTIFF with the input's ``geotags``); or
    ``.hdr`` (ENVI, with an ENVI input's ``map info``). A georeferenced input's mask must keep its georeferencing:
    a GeoTIFF's in a ``.tif``, an ENVI header's ``map info`` in a ``.hdr`` (the two are not converted)."""
    from ..cubefiles import PngRows, TiffMaskRows

    suf = os.path.splitext(str(out))[1].lower()
    mapped = bool(envi_map and "map info" in envi_map)
    if suf not in (".png", ".tif", ".tiff", ".hdr"):
        raise ValueError(f"--out {str(out)!r} must be a .png, .tif or ENVI .hdr mask")
    if mapped and suf != ".hdr":
        raise ValueError(f"--out {str(out)!r}: the ENVI cube is georeferenced (its header's 'map info'); give a .hdr "
                         "mask (an ENVI mask keeps its map info; a PNG or GeoTIFF mask here would drop it)")
    if geotags and suf not in (".tif", ".tiff"):
        raise ValueError(f"--out {str(out)!r}: the cube is georeferenced; give a .tif mask (a GeoTIFF keeps its "
                         "transform and CRS; a PNG or ENVI mask here would drop them)")
    if suf in (".tif", ".tiff"):
        return TiffMaskRows(out, shape[0], shape[1], geotags)
    if suf == ".hdr":
        return _EnviMaskRows(out, shape, dict(envi_map or {}))
    return PngRows(out, shape[0], shape[1])


def mask_rows(mask: np.ndarray) -> np.ndarray:
    """A boolean mask's rows as a mask file stores them: uint8, skin 255, not skin 0."""
    return np.asarray(mask, dtype=bool).view(np.uint8) * np.uint8(255)


def write_mask(out: StrPath, mask: ArrayLike, geotags: list | None = None, envi_map: dict | None = None) -> None:
    """A whole boolean (H, W) mask written by ``_mask_writer`` (the one way masks are written: ``detect_file``
    streams its rows through the same writers), atomically: ``.png``, ``.tif`` or ``.hdr`` by ``out``'s suffix."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ValueError(f"a mask must be (H, W), got shape {m.shape}")
    writer = _mask_writer(out, (m.shape[0], m.shape[1]), geotags or [], envi_map)
    try:
        writer.write_rows(mask_rows(m))
    except BaseException as e:
        writer.abort(e)
        raise
    writer.close()


def _finite_rows(cf: Any, r0: int, r1: int, where: str) -> np.ndarray:
    """``cf.read_rows(r0, r1)``, refused naming the file (``where``) when it holds NaN or infinite values (as
    ``load_cube`` refuses a cube read whole)."""
    block = cf.read_rows(r0, r1)
    if not (np.isfinite(block.min()) and np.isfinite(block.max())):  # NaN propagates through both
        raise ValueError(f"{where} holds NaN or infinite values")
    return block


def detect_file(det: OnboardDetector, cube: Any, config: ArrayLike, out: StrPath | None = None,
                tile_rows: int | None = None, negative: str = "error", min_reflectance: float | None = None,
                bands: Sequence[float] | None = None, option: str = "--cube",
                max_megapixels: float = MAX_MEGAPIXELS) -> dict:
    """Detect skin in a cube file of one frame (``cubefiles.open_cube``: ``.npy`` + sidecar, ENVI, GeoTIFF; or an
    open ``CubeFile``), ``tile_rows`` rows at a time (None: ``TILE_BYTES`` of the input): the model's bands read as they are or synthesised
    (``band_plan``; ``bands`` overrides the file's wavelengths; a cube without any must hold the model's four
    bands in its order), the mask written rows by rows to ``out`` (``_mask_writer``: ``.png``; ``.tif``, a GeoTIFF
    keeping a GeoTIFF input's georeferencing; ``.hdr``, ENVI keeping an ENVI input's map info) through a temporary file renamed at the end. The reflectance range is checked over
    the whole frame (``check_reflectance_range``, naming the file; a value above ``REFLECTANCE_CEILING`` too)
    before the rename: on refusal nothing is written. The mask
    equals ``det`` on the whole frame in memory. Returns ``skin_pixels``, ``pixels``, ``shape`` (H, W),
    ``out_of_domain``, ``plan`` ("reorder" or "synthesis"), ``clipped_values`` (with ``negative="clip"``) and
    ``reflectance_range``."""
    from ..cubefiles import CubeFile, open_cube

    _check_tile_rows(tile_rows)
    cf = cube if isinstance(cube, CubeFile) else open_cube(cube, option, max_megapixels,
                                                            need_wavelengths=bands is None)
    nb, H, W = cf.shape
    tile_rows = _check_tile_rows(tile_rows, cf.shape)
    cube_bands = list(bands) if bands is not None else cf.bands
    where = f"{option} {str(cf.path)!r}"
    if cube_bands is not None and len(cube_bands) != nb:
        raise ValueError(f"--bands gives {len(cube_bands)} bands, but {where} holds {nb}")
    if cube_bands is None or not det.bands_nm:
        if nb != det.n_bands:
            raise ValueError(f"{where} holds {nb} bands and gives no wavelengths; the model needs its "
                             f"{len(det.bands_nm)} bands ({det.bands_nm} nm) in that order, or wavelengths to "
                             "pick or synthesise them from")
        plan: dict = {"kind": "reorder", "order": list(range(nb))}
    else:
        try:
            plan = band_plan(cube_bands, cf.fwhm, plan_bands(det))
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
    c = np.asarray(config, dtype=np.float64).reshape(1, -1)
    writer = None if out is None else _mask_writer(out, (H, W), cf.geotags, cf.envi_map)
    low, high, over, skin, clipped = np.inf, -np.inf, 0, 0, 0
    ood = np.zeros(1, bool)
    try:
        for r0 in range(0, H, tile_rows):
            r1 = min(r0 + tile_rows, H)
            x = apply_plan(plan, _finite_rows(cf, r0, r1, where))
            t_lo, t_hi = float(x.min()), float(x.max())
            low, high = min(low, t_lo), max(high, t_hi)
            if t_hi > REFLECTANCE_MAX:
                over += int(np.count_nonzero(x > REFLECTANCE_MAX))
            res = det(x[None], c, negative=negative, min_reflectance=min_reflectance, range_check=False)
            m = res["mask"][0]
            skin += int(np.count_nonzero(m))
            ood = res["out_of_domain"]
            if "clipped_values" in res:
                clipped += int(res["clipped_values"][0])
            if writer is not None:
                writer.write_rows(mask_rows(m))
        check_reflectance_range(low, high, over / (det.n_bands * H * W), where)
    except BaseException as e:
        if writer is not None:
            writer.abort(e)
        raise
    if writer is not None:
        writer.close()
    doc = {"skin_pixels": skin, "pixels": H * W, "shape": [H, W], "out_of_domain": ood.tolist(),
           "plan": plan["kind"], "reflectance_range": [low, high]}
    if cube_bands is None and det.bands_nm:  # read as the model's bands, in its order: say so (a sidecar-less .npy)
        doc["bands_assumed"] = list(det.bands_nm)
    if negative == "clip":
        doc["clipped_values"] = [clipped]
    return doc


def calibrate_file(cube: Any, out: StrPath, panels: Sequence[tuple[Sequence[int], ArrayLike]] | None = None,
                   coefficients: tuple[ArrayLike, ArrayLike] | None = None, erode: int = 1,
                   tile_rows: int | None = None, option: str = "--cube",
                   max_megapixels: float = MAX_MEGAPIXELS) -> dict:
    """The empirical line of a signal cube file of one frame (``cubefiles.open_cube``), from reference
    ``panels`` (``elm_fit``'s (region, reflectance); only the panels' rows are read) or saved ``coefficients``
    (gain, offset), applied ``tile_rows`` rows at a time (None: ``TILE_BYTES`` of the input) and written to ``out`` in the input's format (``.npy`` +
    sidecar, ENVI, GeoTIFF with the input's geotags; wavelengths and FWHM carried over) through a temporary file
    renamed at the end; a tile with NaN or infinite reflectance removes it. Returns ``gain``, ``offset``, the fit
    (``signals``, ``references``, ``residual``; None with coefficients), ``shape``, ``reflectance_range`` and
    ``out`` (the path written)."""
    from ..cubefiles import CubeFile, CubeWriter, open_cube, output_path

    _check_tile_rows(tile_rows)
    cf = cube if isinstance(cube, CubeFile) else open_cube(cube, option, max_megapixels)
    nb, H, W = cf.shape
    tile_rows = _check_tile_rows(tile_rows, cf.shape)
    where = f"{option} {str(cf.path)!r}"
    fit = None
    if coefficients is not None:
        gain, offset = (np.asarray(v, np.float64) for v in coefficients)
        if gain.shape != (nb,) or offset.shape != (nb,):
            raise ValueError(f"the coefficients give {gain.shape} gains and {offset.shape} offsets for a cube of "
                             f"{nb} bands")
    else:
        if panels is None or len(panels) < 2:
            raise ValueError(f"ELM needs at least 2 reference panels, got {0 if panels is None else len(panels)}")
        check_panel_regions([roi for roi, _ in panels])
        refs, sig = [], []
        for roi, rho in panels:
            y0, y1, x0, x1 = (int(v) for v in roi)
            if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
                raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} must satisfy 0 <= Y0 < Y1 <= {H} and "
                                 f"0 <= X0 < X1 <= {W}")
            refs.append(panel_reference(rho, nb))
            sig.append(panel_signal(_finite_rows(cf, y0, y1, where), (0, y1 - y0, x0, x1), erode))
        fit = elm_line(np.stack(refs), np.stack(sig))
        gain, offset = fit["gain"], fit["offset"]
    if not np.all(np.isfinite(gain)) or np.any(gain <= 0) or not np.all(np.isfinite(offset)):
        raise ValueError("gain must be finite and > 0 and offset finite in every band")
    dest = output_path(out, cf.format)
    low, high = np.inf, -np.inf
    with CubeWriter(dest, cf.shape, cf.format, cf.bands, cf.fwhm, "reflectance", cf.geotags,
                    {k: v for k, v in cf.envi_map.items()}) as w:
        for r0 in range(0, H, tile_rows):
            r1 = min(r0 + tile_rows, H)
            refl = elm_apply(_finite_rows(cf, r0, r1, where), gain, offset)
            t_lo, t_hi = float(refl.min()), float(refl.max())
            if not (np.isfinite(t_lo) and np.isfinite(t_hi)):
                raise ValueError("the calibrated cube holds NaN or infinite values (check the coefficients)")
            low, high = min(low, t_lo), max(high, t_hi)
            w.write_rows(r0, refl)
    return {"gain": gain, "offset": offset, "fit": fit, "shape": [nb, H, W], "reflectance_range": [low, high],
            "out": str(dest)}
