"""What an evaluation measures in the (NDGRI, NDSI) index plane: a model's false alarms on the earthlib test
spectra and the area of its decision region per configuration, and the ROC of a box model as its boxes scale
about their centres. The per-row decisions and their rates are ``evaluation.metrics``'s."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import cast

import numpy as np
import torch

from ..bands import BAND_MATCH_NM, INDEX_BANDS_NM
from ..detectors.features import ratio_indices
from ..detectors.protocol import false_alarm_rate, inside_box
from .candidates import Candidate
from .metrics import HeldOut, Judged, rate

#: index-plane grid (per axis, over [-1, 1]) on which the decision region of a non-box model is measured
AREA_GRID = 64
ROC_SCALES = tuple(float(x) for x in np.linspace(0.25, 3.0, 23))


def same_bands(a: Sequence[float], b: Sequence[float]) -> bool:
    """Whether two lists of band centres (nm) name the same bands in the same order, each within
    ``bands.BAND_MATCH_NM``."""
    return len(a) == len(b) and all(abs(x - y) <= BAND_MATCH_NM for x, y in zip(a, b))


def is_index_bands(bands_nm: Sequence[float]) -> bool:
    """Whether ``bands_nm`` are the index bands, in order (``same_bands``): the bands the (NDGRI, NDSI) plane,
    the static box and box models read."""
    return same_bands(bands_nm, INDEX_BANDS_NM)


def earthlib_test(bands_nm: Sequence[float] = INDEX_BANDS_NM,
                  indices: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The earthlib test spectra at the band centres ``bands_nm`` (default the index bands): reflectance (m, n)
    float32 and, row for row, their (NDGRI, NDSI, NDVN) (m, 3) (NaN: undefined). ``indices``: whether the bands
    stand for the index bands, in order (default: whether they are them, ``is_index_bands``; a camera with its
    filters a few nm off reads them as such); NaN points otherwise."""
    from ..confusers import band_reflectance

    _, test_R = band_reflectance(list(bands_nm), "test")
    test_R = test_R.float()
    if not (is_index_bands(bands_nm) if indices is None else indices):
        return test_R, torch.full((test_R.shape[0], 3), math.nan)
    return test_R, torch.stack(ratio_indices(test_R), -1)


def judge(cand: Candidate, rows: HeldOut, test_R: torch.Tensor, test_pts: torch.Tensor, floor: float) -> Judged:
    """One model's decisions on the rows (under the brightness ``floor``), its earthlib-test Pfa and region area
    per configuration."""
    X = rows.X_of(cand.features)
    cfg_X = X[rows.first]
    hit = cand.decide(rows.R, X).bool() & (rows.R.mean(-1) > floor)
    bright = test_R.mean(-1) > floor
    if cand.boxes is not None:
        bx = cand.boxes(cfg_X)
        pts = torch.where(bright[:, None], test_pts, torch.full_like(test_pts, math.nan))  # aligned with test_R
        pfa_cfg = false_alarm_rate(bx, pts).double()
        w = (bx[:, 1].clamp(-1, 1) - bx[:, 0].clamp(-1, 1)).clamp_min(0)
        h = (bx[:, 3].clamp(-1, 1) - bx[:, 2].clamp(-1, 1)).clamp_min(0)
        area_cfg = (w * h).double()
    else:
        pfa_cfg = pfa_by_config(cand, cfg_X, test_R, bright)
        area_cfg = (grid_area(cand, cfg_X, rows) if is_index_bands(cand.bands)  # the plane needs the index bands
                    else torch.full((rows.n_cfg,), math.nan, dtype=torch.float64))
    return Judged(hit, pfa_cfg, area_cfg)


def pfa_by_config(cand: Candidate, cfg_X: torch.Tensor, test_R: torch.Tensor, bright: torch.Tensor,
                  chunk: int = 1 << 20) -> torch.Tensor:
    """Per configuration, the fraction of the earthlib test spectra (reflectance (m, 4), as measured) that the
    model calls skin (only ``bright`` ones can be)."""
    m = test_R.shape[0]
    out = torch.empty(cfg_X.shape[0], dtype=torch.float64)
    per = max(1, chunk // m)
    for lo in range(0, cfg_X.shape[0], per):
        c = cfg_X[lo:lo + per]
        X = c.repeat_interleave(m, 0)
        R = test_R.repeat(c.shape[0], 1)
        out[lo:lo + c.shape[0]] = (cand.decide(R, X).reshape(c.shape[0], m) & bright).double().mean(1)
    return out


def grid_area(cand: Candidate, cfg_X: torch.Tensor, rows: HeldOut) -> torch.Tensor:
    """Per configuration, the area of the (NDGRI, NDSI) plane (over [-1, 1]^2) that the model calls skin, at
    the band-pair brightness of that configuration's sunlit skin (median (g + r) / 2 and (n + s) / 2)."""
    lit = rows.label & ~rows.shadow
    pair = torch.stack([(rows.R[:, 0] + rows.R[:, 1]) / 2, (rows.R[:, 2] + rows.R[:, 3]) / 2], -1)
    default = pair[lit].median(0).values if bool(lit.any()) else torch.tensor([0.4, 0.3])
    med = default.expand(rows.n_cfg, 2).clone()
    order = torch.argsort(rows.cfg[lit], stable=True)
    cfg_l, pair_l = rows.cfg[lit][order], pair[lit][order]
    uniq, counts = torch.unique_consecutive(cfg_l, return_counts=True)
    for c, part in zip(uniq.tolist(), torch.split(pair_l, counts.tolist())):  # per configuration (not per pixel)
        med[c] = part.median(0).values
    k = AREA_GRID
    axis = -1 + (torch.arange(k) + 0.5) * (2.0 / k)
    G, S = torch.meshgrid(axis, axis, indexing="ij")
    G, S = G.reshape(-1), S.reshape(-1)
    out = torch.empty(rows.n_cfg, dtype=torch.float64)
    per = max(1, (1 << 20) // (k * k))
    for lo in range(0, rows.n_cfg, per):
        a = med[lo:lo + per]  # (c, 2)
        n = a.shape[0]
        R = torch.stack([a[:, :1] * (1 + G), a[:, :1] * (1 - G), a[:, 1:] * (1 + S), a[:, 1:] * (1 - S)], -1)
        X = cfg_X[lo:lo + per].repeat_interleave(k * k, 0)
        hit = cand.decide(R.reshape(-1, 4).float(), X).reshape(n, k * k)
        out[lo:lo + n] = hit.double().mean(1) * 4.0
    return out


def scaled(b: torch.Tensor, k: float) -> torch.Tensor:
    """Boxes (N, 4+) scaled by ``k`` about their centres in (NDGRI, NDSI) (a fifth column, d1, is kept)."""
    ctr = torch.stack([(b[:, 0] + b[:, 1]) / 2] * 2 + [(b[:, 2] + b[:, 3]) / 2] * 2, -1)
    return torch.cat([ctr + float(k) * (b[:, :4] - ctr), b[:, 4:]], -1)


def roc(cand: Candidate, static: Candidate, rows: HeldOut, test_pts, scales: Sequence[float], floor: float) -> dict:
    """Pd (sunlit) against Pfa as every box is scaled about its centre, for ``cand`` and the static box."""
    out: dict[str, list] = {"scales": [float(k) for k in scales]}
    lit = rows.label & ~rows.shadow
    nonskin = ~rows.label
    for key, c in (("learned", cand), ("static", static)):
        boxes_of = cast(Callable, c.boxes)  # both are box models
        X = rows.X_of(c.features)
        bx = boxes_of(X)
        cb = boxes_of(X[rows.first])
        pts = []
        for k in scales:
            hit = inside_box(scaled(bx, k), rows.g, rows.s, rows.v) & (rows.R.mean(-1) > floor)
            pts.append([float(false_alarm_rate(scaled(cb, k), test_pts).mean()), rate(hit, lit),
                        rate(hit, nonskin)])
        out[key] = pts
    return out


__all__ = ["AREA_GRID", "ROC_SCALES", "earthlib_test", "grid_area", "is_index_bands", "judge", "pfa_by_config",
           "roc", "same_bands", "scaled"]
