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
        elif isinstance(b, (tuple, list)):
            out.append(Band(float(b[0]), float(b[1])))
        else:
            out.append(Band(float(b)))
    if not out:
        raise ValueError("bands must name at least one band")
    return tuple(out)


def parse_bands(text: str) -> tuple[Band, ...]:
    """Parse ``"544,633,1080/20,1580/40"`` (centre[/fwhm] in nm, comma separated)."""
    out = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        c, _, f = item.partition("/")
        try:
            out.append(Band(float(c), float(f) if f else 0.0))
        except ValueError as e:
            raise ValueError(f"bad band {item!r} in --bands (use centre[/fwhm] in nm): {e}") from None
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


def band_sampling(bands: Sequence[Band], step_nm: float = 1.0, dtype=None, device=None):
    """A wavelength grid that samples every band and the matrix that averages it back to bands.

    Returns ``(grid, W)``; evaluate a model on ``grid`` and multiply by ``W`` to get band values.
    Monochromatic bands contribute their centre only.
    """
    bands = as_bands(bands)
    pts: list[float] = []
    for b in bands:
        if b.fwhm_nm == 0:
            pts.append(b.center_nm)
        else:
            s_lo, s_hi = b.support
            n = max(int(math.ceil((s_hi - s_lo) / step_nm)), 8) + 1
            pts.extend(torch.linspace(s_lo, s_hi, n, dtype=torch.float64).tolist())
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
