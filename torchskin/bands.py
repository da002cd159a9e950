"""Spectral bands: ``Band(center_nm, fwhm_nm)`` with Gaussian response; fwhm 0 means monochromatic.

Band values of a spectrum are response-weighted means over wavelength (a flat source spectrum; weight by
the source yourself when it matters). Shapes: spectra are ``(..., n_grid)``, band values ``(..., n_bands)``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch

from ._checks import as_tensor

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
SUPPORT_FWHM = 1.5  # a band's response is truncated at centre +- 1.5 FWHM (+- 3.5 sigma)
#: most wavelengths a sampling grid (``band_sampling``, ``tissue.wavelength_grid``) may have: refused before
#: anything is allocated (1e6 points is about 1 pm steps over the model's 400-1700 nm); ``band_sampling``'s
#: weight matrix (grid x bands) may hold at most 16 times as many entries
MAX_GRID_POINTS = 1_000_000


def _model_range() -> tuple[float, float]:
    from .tissue import MODEL_RANGE_NM  # lazy: tissue imports this module (through optics)

    return MODEL_RANGE_NM


@dataclass(frozen=True)
class Band:
    """A spectral band: centre and full width at half maximum of a Gaussian response, both in nm."""

    center_nm: float
    fwhm_nm: float = 0.0

    def __post_init__(self):
        if not (self.center_nm > 0 and math.isfinite(self.center_nm)):
            raise ValueError(f"center_nm must be a positive finite wavelength in nm, got {self.center_nm}")
        if not (self.fwhm_nm >= 0 and math.isfinite(self.fwhm_nm)):
            raise ValueError(f"fwhm_nm must be >= 0 nm, got {self.fwhm_nm}")

    @property
    def support(self) -> tuple[float, float]:
        h = SUPPORT_FWHM * self.fwhm_nm
        return self.center_nm - h, self.center_nm + h


#: The thesis's detection system: green, red, NIR, SWIR (monochromatic by default).
DEFAULT_BANDS: tuple[Band, ...] = (Band(544.0), Band(633.0), Band(1080.0), Band(1580.0))


def as_bands(bands: Iterable[Band | float | tuple[float, float]] | None) -> tuple[Band, ...]:
    """Normalise a band specification (Band objects, centres, or (centre, fwhm) pairs)."""
    if bands is None:
        return DEFAULT_BANDS
    out = []
    for b in bands:
        if isinstance(b, Band):
            out.append(b)
            continue
        try:
            if isinstance(b, (tuple, list)):
                if len(b) not in (1, 2):
                    raise ValueError
                out.append(Band(*(float(x) for x in b)))
            else:
                out.append(Band(float(b)))
        except (TypeError, ValueError) as e:
            msg = f": {e}" if str(e) else ""
            raise ValueError(f"band {b!r} must be a centre or (centre, fwhm) in nm{msg}") from None
    if not out:
        raise ValueError("bands must name at least one band")
    return tuple(out)


def check_band_within(band: Band, lo: float, hi: float) -> None:
    """``ValueError`` unless the band's response (centre +- ``SUPPORT_FWHM`` FWHM) lies within ``lo..hi`` nm."""
    s_lo, s_hi = band.support
    if s_lo >= lo - 1e-9 and s_hi <= hi + 1e-9:
        return
    c, f = band.center_nm, band.fwhm_nm
    if not (lo <= c <= hi):
        raise ValueError(f"band {c:g}/{f:g} nm: the centre lies outside the model's {lo:g}-{hi:g} nm")
    fmax = min(c - lo, hi - c) / SUPPORT_FWHM
    raise ValueError(f"band {c:g}/{f:g} nm: its response (centre +- {SUPPORT_FWHM:g} FWHM) spans {s_lo:g}..{s_hi:g}"
                     f" nm, outside the model's {lo:g}-{hi:g} nm; the FWHM may be at most {fmax:.4g} nm at this centre")


def parse_bands(text: str, within: tuple[float, float] | None = None) -> tuple[Band, ...]:
    """Parse ``"544,633,1080/20,1580/40"`` (centre[/fwhm] in nm, comma separated). Every band's response must
    lie ``within`` (lo, hi) nm, by default the skin model's 400-1700 nm (``tissue.MODEL_RANGE_NM``)."""
    lo, hi = _model_range() if within is None else within
    out = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        c, _, f = item.partition("/")
        try:
            band = Band(float(c), float(f) if f else 0.0)
            check_band_within(band, lo, hi)
        except ValueError as e:
            raise ValueError(f"bad band {item!r} in --bands (use centre[/fwhm] in nm): {e}") from None
        out.append(band)
    return as_bands(out)


def response_matrix(grid: torch.Tensor, bands: Sequence[Band]) -> torch.Tensor:
    """Weights ``(n_grid, n_bands)``, each column summing to 1, so that ``spectrum @ W`` gives band values.

    ``grid`` is an increasing 1-D wavelength tensor (nm). Gaussian bands use trapezoid quadrature on the
    grid; monochromatic bands use linear-interpolation weights. Raises ``ValueError`` if a band's support
    is not inside the grid.
    """
    grid = as_tensor(grid)
    if grid.ndim != 1 or grid.numel() < 1:
        raise ValueError("grid must be a 1-D wavelength tensor")
    lo, hi = float(grid[0]), float(grid[-1])
    cols = []
    for b in bands:
        s_lo, s_hi = b.support
        if s_lo < lo - 1e-9 or s_hi > hi + 1e-9:
            raise ValueError(
                f"band {b.center_nm:g}/{b.fwhm_nm:g} nm needs wavelengths {s_lo:g}..{s_hi:g} nm;"
                f" the grid covers only {lo:g}..{hi:g} nm"
            )
        if b.fwhm_nm == 0 or grid.numel() == 1:
            if grid.numel() == 1:
                w = torch.ones_like(grid)
            else:
                i = int(torch.searchsorted(grid, torch.tensor([b.center_nm], dtype=grid.dtype, device=grid.device), right=True).clamp(1, grid.numel() - 1))
                t = (b.center_nm - float(grid[i - 1])) / float(grid[i] - grid[i - 1])
                w = torch.zeros_like(grid)
                w[i - 1] = 1 - t
                w[i] = t
        else:
            sigma = b.fwhm_nm * FWHM_TO_SIGMA
            g = torch.exp(-0.5 * ((grid - b.center_nm) / sigma) ** 2)
            g = torch.where((grid >= s_lo) & (grid <= s_hi), g, torch.zeros_like(g))
            dx = torch.diff(grid)
            trap = torch.zeros_like(grid)
            trap[:-1] += 0.5 * dx
            trap[1:] += 0.5 * dx
            w = g * trap
            if float(w.sum()) <= 0:
                raise ValueError(f"grid too coarse for band {b.center_nm:g}/{b.fwhm_nm:g} nm")
            w = w / w.sum()
        cols.append(w)
    return torch.stack(cols, dim=-1)


def band_integrate(values: torch.Tensor, grid: torch.Tensor, bands: Sequence[Band]) -> torch.Tensor:
    """Band values ``(..., n_bands)`` of spectra ``values`` ``(..., n_grid)`` sampled on ``grid``."""
    bands = as_bands(bands)
    grid = as_tensor(grid, like=values)
    if values.shape[-1] != grid.shape[-1]:
        raise ValueError(f"values' last axis ({values.shape[-1]}) must match the grid length ({grid.shape[-1]})")
    return values @ response_matrix(grid, bands)


def band_sampling(bands: Sequence[Band], step_nm: float = 1.0, dtype=None, device=None,
                  within: tuple[float, float] | None = None):
    """A wavelength grid that samples every band and the matrix that averages it back to bands.

    Returns ``(grid, W)``; evaluate a model on ``grid`` and multiply by ``W`` to get band values.
    Monochromatic bands contribute their centre only. Every band's response must lie ``within`` (lo, hi) nm,
    by default the skin model's 400-1700 nm, and the grid may hold at most ``MAX_GRID_POINTS`` wavelengths:
    both are checked before anything is allocated.
    """
    bands = as_bands(bands)
    if isinstance(step_nm, bool) or not isinstance(step_nm, (int, float)) or not (
            math.isfinite(step_nm) and step_nm > 0):
        raise ValueError(f"step_nm must be a positive finite number of nm, got {step_nm!r}")
    lo, hi = _model_range() if within is None else within
    counts = []
    for b in bands:
        check_band_within(b, lo, hi)
        span = (b.support[1] - b.support[0]) / step_nm
        counts.append(1 if b.fwhm_nm == 0 else (max(math.ceil(span), 8) + 1 if span <= MAX_GRID_POINTS else span))
    if sum(counts) > MAX_GRID_POINTS:
        raise ValueError(f"band sampling at {step_nm:g} nm steps would need {sum(counts):.3g} wavelengths; at most "
                         f"{MAX_GRID_POINTS} (use fewer or narrower bands, or a larger step)")
    if sum(counts) * len(bands) > 16 * MAX_GRID_POINTS:
        raise ValueError(f"band sampling of {len(bands)} bands would need a {sum(counts):.3g} x {len(bands)} weight "
                         f"matrix; at most {16 * MAX_GRID_POINTS} entries (use fewer or narrower bands)")
    pts: list[float] = []
    for b, n in zip(bands, counts):
        if b.fwhm_nm == 0:
            pts.append(b.center_nm)
        else:
            s_lo, s_hi = b.support
            pts.extend(torch.linspace(s_lo, s_hi, int(n), dtype=torch.float64).tolist())
    uniq = sorted(set(round(p, 9) for p in pts))
    grid = torch.tensor(uniq, dtype=dtype or torch.get_default_dtype(), device=device)
    cols = []
    for b in bands:  # per-band weights on the sub-grid belonging to that band only
        if b.fwhm_nm == 0:
            w = (torch.abs(grid - b.center_nm) < 1e-6).to(grid.dtype)
        else:
            s_lo, s_hi = b.support
            sel = (grid >= s_lo - 1e-9) & (grid <= s_hi + 1e-9)
            sub = grid[sel]
            w = torch.zeros_like(grid)
            w[sel] = response_matrix(sub, [b])[:, 0]
        cols.append(w / w.sum())
    return grid, torch.stack(cols, dim=-1)
