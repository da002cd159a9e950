"""The empirical line (ELM) of camera frames, numpy only: panel signals (``panel_signal``), the line through
reference panels (``elm_fit``, ``elm_line``) and its application (``elm_apply``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike


def panel_signal(frame: ArrayLike, roi: Sequence[int], erode: int = 1) -> np.ndarray:
    """Per-band median of ``frame`` (bands, H, W) over the region ``roi`` = (y0, y1, x0, x1) shrunk by ``erode``
    pixels on every side (the panel's edges mix with the background)."""
    f = np.asarray(frame)
    if f.ndim != 3:
        raise ValueError(f"frame must be (bands, H, W), got shape {f.shape}")
    if int(erode) < 0:
        raise ValueError(f"erode must be >= 0 pixels, got {erode}")
    y0, y1, x0, x1 = (int(v) for v in roi)
    H, W = f.shape[1:]
    if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
        raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} must satisfy 0 <= Y0 < Y1 <= {H} and 0 <= X0 < X1 <= {W}")
    e = int(erode)
    if y1 - y0 <= 2 * e or x1 - x0 <= 2 * e:
        raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} has no interior pixel after eroding {e} px per side")
    v = f[:, y0 + e:y1 - e, x0 + e:x1 - e].reshape(f.shape[0], -1).astype(np.float64)
    if not np.isfinite(v).all():
        raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} holds NaN or infinite values")
    return np.median(v, axis=1)


def check_panel_regions(rois: Sequence[Sequence[int]]) -> None:
    """``ValueError`` when two panel regions (y0, y1, x0, x1) are the same or overlap: two panels cannot share a
    pixel, so one of them is mistyped, and the line through them would be fitted to one panel's signal twice.

    >>> check_panel_regions([(0, 4, 0, 4), (0, 4, 4, 8)])  # side by side: fine
    >>> check_panel_regions([(0, 4, 0, 4), (2, 6, 2, 6)])
    Traceback (most recent call last):
    ...
    ValueError: panel regions 0:4:0:4 and 2:6:2:6 overlap (4 pixels): each panel needs its own region
    """
    boxes = [tuple(int(v) for v in r) for r in rois]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            (a0, a1, b0, b1), (c0, c1, d0, d1) = boxes[i], boxes[j]
            n = max(0, min(a1, c1) - max(a0, c0)) * max(0, min(b1, d1) - max(b0, d0))
            if n:
                what = "are the same region" if boxes[i] == boxes[j] else f"overlap ({n} pixels)"
                raise ValueError(f"panel regions {':'.join(map(str, boxes[i]))} and {':'.join(map(str, boxes[j]))} "
                                 f"{what}: each panel needs its own region")


def elm_fit(frame: ArrayLike, panels: Sequence[tuple[Sequence[int], ArrayLike]], erode: int = 1) -> dict:
    """Empirical line L = gain·ρ + offset per band (eqs 2.5.5-2.5.6) from reference panels in ``frame``
    (bands, H, W): ``panels`` is a sequence of (roi, reflectance), the reflectance a scalar or one value per
    band in (0, 1]; the panels' regions must not overlap (``check_panel_regions``). Two panels give the exact
    line through them; more give the least-squares line. ``residual``: per band, the RMS over the panels of the
    fitted minus the known reflectance ((L - offset) / gain - ρ; 0 for two panels)."""
    f = np.asarray(frame)
    if f.ndim != 3:
        raise ValueError(f"frame must be (bands, H, W), got shape {f.shape}")
    if len(panels) < 2:
        raise ValueError(f"ELM needs at least 2 reference panels, got {len(panels)}")
    nb = f.shape[0]
    check_panel_regions([roi for roi, _ in panels])
    refs, sig = [], []
    for roi, rho in panels:
        refs.append(panel_reference(rho, nb))
        sig.append(panel_signal(f, roi, erode))
    return elm_line(np.stack(refs), np.stack(sig))


def panel_reference(rho: ArrayLike, nb: int) -> np.ndarray:
    """A panel's reflectance per band (``nb``) from one value or one per band, each in (0, 1]."""
    r = np.broadcast_to(np.asarray(rho, dtype=np.float64), (nb,)) if np.ndim(rho) == 0 else np.asarray(rho, np.float64)
    if r.shape != (nb,):
        raise ValueError(f"panel reflectance must be one value or {nb} (one per band), got {np.shape(rho)}")
    if not (np.all(r > 0) and np.all(r <= 1)):
        raise ValueError(f"panel reflectance must lie in (0, 1], got {r.tolist()}")
    return r


def elm_line(R: np.ndarray, L: np.ndarray) -> dict:
    """The empirical line per band through panels of known reflectance ``R`` and measured signal ``L``, both
    (panels, bands): ``elm_fit``'s result (``calibrate_file`` measures the signals from row tiles)."""
    dR = R - R.mean(0)
    var = (dR ** 2).sum(0)
    if np.any(var < 1e-12):
        bad = np.flatnonzero(var < 1e-12).tolist()
        raise ValueError(f"panel reflectances must differ in every band (band(s) {bad} have equal references)")
    gain = (dR * (L - L.mean(0))).sum(0) / var
    if np.any(gain <= 0):
        bad = np.flatnonzero(gain <= 0).tolist()
        raise ValueError(f"panel signals do not grow with reflectance in band(s) {bad}: regions or reflectances "
                         "swapped, or a panel saturated or in shadow?")
    offset = L.mean(0) - gain * R.mean(0)
    resid = np.sqrt((((L - offset) / gain - R) ** 2).mean(0))
    return {"gain": gain, "offset": offset, "signals": L, "references": R, "residual": resid}


def elm_apply(cube: ArrayLike, gain: ArrayLike, offset: ArrayLike) -> np.ndarray:
    """Reflectance (float32) of signals ``cube`` (bands, H, W) or (B, bands, H, W): (L - offset) / gain."""
    x = np.asarray(cube)
    g, o = np.asarray(gain, np.float64), np.asarray(offset, np.float64)
    if x.ndim not in (3, 4) or g.shape != (x.shape[-3],) or o.shape != g.shape:
        raise ValueError(f"cube must be (bands, H, W) or (B, bands, H, W) with one gain and offset per band; got "
                         f"cube {x.shape}, gain {g.shape}, offset {o.shape}")
    if not np.all(np.isfinite(g)) or np.any(g <= 0) or not np.all(np.isfinite(o)):
        raise ValueError("gain must be finite and > 0 and offset finite in every band")
    inv = (1.0 / g)[:, None, None]
    return ((x - o[:, None, None]) * inv).astype(np.float32)
