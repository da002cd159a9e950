"""The model's bands from any cube, numpy only: a cube's bands matched to the model's (``match_bands``), or the
model's bands synthesised from a cube's spectrum (``band_plan``, ``apply_plan``)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, cast

import numpy as np

from ..bands import BAND_MATCH_NM  # how far a cube's band centre may lie from the model's

if TYPE_CHECKING:
    from ..bands import Band
    from .runtime import _Model

#: the widest step (nm) between a cube's samples inside (or bracketing) a model band's response that
#: ``band_plan`` interpolates across: a wider gap (a cube with a missing detector range) is refused
MAX_SAMPLE_GAP_NM = 50.0


def match_bands(cube_bands: Sequence[float], model_bands: Sequence[float], tol_nm: float = BAND_MATCH_NM) -> list[int]:
    """For each of the model's bands, the index of the cube's band at that wavelength (within ``tol_nm``): the
    order to read the cube in. ``ValueError`` naming the band when the cube has none there.

    >>> match_bands([1580, 544, 1080, 633], [544, 633, 1080, 1580])
    [1, 3, 2, 0]
    >>> match_bands([544, 633, 1080], [544, 633, 1080, 1580])
    Traceback (most recent call last):
    ...
    ValueError: the cube's bands (544, 633, 1080 nm) do not include the model's 1580 nm band (within 2 nm)
    """
    cube = np.asarray(cube_bands, dtype=np.float64)
    order = []
    for b in model_bands:
        d = np.abs(cube - float(b))
        if not d.size or d.min() > tol_nm:
            raise ValueError(f"the cube's bands ({', '.join(f'{v:g}' for v in cube)} nm) do not include the model's "
                             f"{float(b):g} nm band (within {tol_nm:g} nm)")
        order.append(int(d.argmin()))
    return order


def band_plan(cube_bands: Sequence[float], cube_fwhm: Sequence[float] | None,
              model_bands: Sequence[float] | Sequence[Band], model_fwhm: Sequence[float] | None = None) -> dict:
    """How to read the model's bands from a cube with bands ``cube_bands`` (nm): ``{"kind": "reorder", "order":
    [...]}`` when the cube has exactly the model's bands (``match_bands``: used as they are, reordered), else
    ``{"kind": "synthesis", "matrix": (n_model, n_cube) float64}``, each row summing to 1: the model's band
    (``model_bands`` as centres with ``model_fwhm``, 0 = monochromatic: the renderer's default bands; or as
    ``bands.Band``, a measured response curve included) by the band response model of the renderer
    (``bands.response_weights``) on the cube's spectrum, linearly interpolated between its samples onto a 1 nm grid
    over the band's support. The cube's own FWHM (``cube_fwhm``) is not deconvolved: its samples are taken as the
    spectrum at their centres. ``ValueError`` naming the band and the cube's range when the cube does not cover
    a band, or leaves a gap over ``MAX_SAMPLE_GAP_NM`` inside it.

    >>> band_plan([1580, 544, 1080, 633], None, [544, 633, 1080, 1580])
    {'kind': 'reorder', 'order': [1, 3, 2, 0]}
    >>> p = band_plan(range(450, 1651, 10), None, [544, 633, 1080, 1580])
    >>> p["kind"], p["matrix"].shape, [round(float(w), 2) for w in p["matrix"][0, 9:11]]
    ('synthesis', (4, 121), [0.6, 0.4])
    """
    from ..bands import Band, response_weights

    cb = np.asarray([float(b) for b in cube_bands], dtype=np.float64)
    mf = [0.0] * len(model_bands) if model_fwhm is None else [float(f) for f in model_fwhm]
    bands = [b if isinstance(b, Band) else Band(float(cast(float, b)), f) for b, f in zip(model_bands, mf)]
    if len(cb) == len(bands):
        try:
            return {"kind": "reorder", "order": match_bands(cb.tolist(), [b.center_nm for b in bands])}
        except ValueError:
            pass
    order = np.argsort(cb)
    x = cb[order]
    lo, hi = float(x[0]), float(x[-1])
    spans = []
    for band in bands:  # each band's response, where the cube must hold samples
        c, f = band.center_nm, band.fwhm_nm
        s_lo, s_hi = band.support
        near = np.abs(x - c)
        if f == 0 and near.min() <= BAND_MATCH_NM and not (lo <= c <= hi):
            s_lo = s_hi = float(x[near.argmin()])  # a band just past the cube's last sample, within the match
        spans.append((s_lo, s_hi))
    missing = [k for k, (s_lo, s_hi) in enumerate(spans) if len(x) < 2 or s_lo < lo - 1e-9 or s_hi > hi + 1e-9]
    if missing:  # every band the cube lacks, before any gap inside one it spans
        k = missing[0]
        more = [f"{bands[j].center_nm:g}" for j in missing[1:]]
        raise ValueError(f"the cube's {len(x)} bands span {lo:g}..{hi:g} nm, which does not cover the model's "
                         f"{bands[k].center_nm:g} nm band (its response needs {spans[k][0]:g}..{spans[k][1]:g} nm)"
                         + (f", nor its {', '.join(more)} nm band{'s' * (len(more) > 1)}" if more else ""))
    rows = []
    for band, (s_lo, s_hi) in zip(bands, spans):
        c, f = band.center_nm, band.fwhm_nm
        a = max(int(np.searchsorted(x, s_lo, side="right")) - 1, 0)
        b = min(int(np.searchsorted(x, s_hi, side="left")), len(x) - 1)
        gap = float(np.diff(x[a:b + 1]).max()) if b > a else 0.0
        if gap > MAX_SAMPLE_GAP_NM:
            raise ValueError(f"the cube's bands ({lo:g}..{hi:g} nm) leave a {gap:g} nm gap inside the model's {c:g} nm "
                             f"band (at most {MAX_SAMPLE_GAP_NM:g} nm between samples is interpolated)")
        grid = np.array([s_lo]) if f == 0 else np.linspace(s_lo, s_hi, max(math.ceil(s_hi - s_lo), 8) + 1)
        interp = np.stack([response_weights(x, g, 0.0) for g in np.clip(grid, lo, hi)])  # cube samples -> grid
        w = response_weights(grid, s_lo if f == 0 else c, f, band.response) @ interp
        row = np.zeros(len(x))
        row[order] = w
        rows.append(row)
    return {"kind": "synthesis", "matrix": np.stack(rows)}


def apply_plan(plan: dict, block: np.ndarray) -> np.ndarray:
    """The model's bands (n_model, rows, W) float32 from a cube's rows ``block`` (n_cube, rows, W) by ``plan``
    (a synthesis summed in float64 per pixel, then rounded)."""
    if plan["kind"] == "reorder":
        order = plan["order"]
        return block if order == list(range(block.shape[0])) else np.ascontiguousarray(block[order])
    m = plan["matrix"]
    out = np.zeros((m.shape[0], *block.shape[1:]), dtype=np.float64)
    for j in range(m.shape[0]):  # per element, over the band's few non-zero weights: a pixel's value depends on
        for k in np.flatnonzero(m[j]):  # its spectrum alone, not on the tile's size or its place in it (a GEMM's
            out[j] += m[j, k] * block[k].astype(np.float64)  # blocking would change the rounding with the tile)
    return out.astype(np.float32)


def plan_bands(det: _Model) -> list[Band]:
    """The model's bands for ``band_plan``: its metadata ``bands`` (response curves included), or, in exports
    without it, its centres with ``model_fwhm``."""
    from ..bands import Band

    if det.band_set is not None:
        return list(det.band_set.bands)
    fwhm = model_fwhm(det) or [0.0] * len(det.bands_nm)
    return [Band(float(c), float(f)) for c, f in zip(det.bands_nm, fwhm)]


def model_fwhm(det: _Model) -> list[float] | None:
    """The model's band FWHM (nm) from its metadata ``bands`` (or, in exports without it, ``fwhm_nm``); None
    (monochromatic, the renderer's default bands) when it has none."""
    if det.band_set is not None:
        return [b.fwhm_nm for b in det.band_set]
    try:
        f = json.loads(det.meta.get("fwhm_nm", "null"))
        return None if f is None else [float(v) for v in f]
    except (ValueError, TypeError):
        return None
