"""Skin indices, the rules detector (eq 2.5.10) and the Bhattacharyya coefficient (eq 4.2.1).

Index signs (DESIGN.md): NDSI = (ρ1080 - ρ1580)/(ρ1080 + ρ1580); NDGRI = (ρ544 - ρ633)/(ρ544 + ρ633), green
minus red (the thesis prints eq 2.5.9 the other way round, but its negative bounds need green minus red).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, TypeVar

import torch

from ._checks import TensorLike, as_tensor
from .bands import DEFAULT_BANDS, INDEX_BANDS_NM, Band, as_bands

if TYPE_CHECKING:
    import numpy as np

#: torch tensors or numpy arrays: ``normalized_difference`` takes either
ArrayT = TypeVar("ArrayT", "torch.Tensor", "np.ndarray")


def normalized_difference(a: ArrayT, b: ArrayT) -> ArrayT:
    """(a - b) / (a + b); NaN where a + b == 0. The one home of the formula: tensors (``ratio_indices``, the
    renderer's ``elm_indices``) or numpy arrays (``dataset.schema.Rows.nd``), the same steps in their dtype."""
    return (a - b) / (a + b)


def ratio_indices(R: torch.Tensor, zero_undefined: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The three normalised differences of reflectance in the four index bands (g, r, n, s) = 544, 633, 1080,
    1580 nm (``INDEX_BANDS_NM``): NDGRI = (g - r) / (g + r) and NDSI = (n - s) / (n + s) (eq 2.5.10's indices)
    and NDVN = ((g + r) - (n + s)) / (g + r + n + s), the visible/NIR balance. The one home of these formulas
    (the onboard runtime evaluates them through the exported graphs).

    Args:
        R: reflectance with the four bands on the last axis, in ``INDEX_BANDS_NM`` order.
        zero_undefined: False (default): plain ratios, NaN where a band sum is 0 (undefined indices: no box
            holds them). True: 0 wherever the band sum is not positive (finite inputs for a network).

    Shape:
        R: (..., 4); each output: (...).

    Returns:
        (NDGRI, NDSI, NDVN).

    >>> g, s, v = ratio_indices(torch.tensor([[0.3, 0.6, 0.5, 0.1], [0.0, 0.0, 0.5, 0.1]]))
    >>> [round(x, 4) for x in (g[0].item(), s[0].item(), v[0].item())], bool(g[1].isnan())
    ([-0.3333, 0.6667, 0.2], True)
    >>> ratio_indices(torch.zeros(1, 4), zero_undefined=True)
    (tensor([0.]), tensor([0.]), tensor([0.]))
    """
    g, r, n, s = R.unbind(-1)
    if not zero_undefined:  # the normalised difference: NDGRI and NDSI exactly as ``indices``
        return normalized_difference(g, r), normalized_difference(n, s), normalized_difference(g + r, n + s)
    vis, nir = g + r, n + s
    tiny = torch.finfo(R.dtype).tiny

    def nd(a: torch.Tensor, b: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        return torch.where(d > 0, (a - b) / d.clamp_min(tiny), torch.zeros_like(d))

    return nd(g, r, vis), nd(n, s, nir), nd(vis, nir, vis + nir)


def ndgri(green: TensorLike, red: TensorLike) -> torch.Tensor:
    """Normalized Difference Green-Red Index, (ρ544 - ρ633)/(ρ544 + ρ633): green minus red (DESIGN.md; the
    thesis prints eq 2.5.9 the other way round).

    Args:
        green: reflectance at 544 nm.
        red: reflectance at 633 nm.

    Shape:
        The two broadcast; the result has the broadcast shape (NaN where both are 0).

    Returns:
        NDGRI in [-1, 1]: negative for skin (redder than green).

    >>> round(float(ndgri(0.30, 0.62)), 4)
    -0.3478
    """
    green = as_tensor(green)
    return normalized_difference(green, as_tensor(red, like=green))


def ndsi(nir: TensorLike, swir: TensorLike) -> torch.Tensor:
    """Normalized Difference Skin Index, eq 2.5.8: (ρ1080 - ρ1580)/(ρ1080 + ρ1580).

    Args:
        nir: reflectance at 1080 nm.
        swir: reflectance at 1580 nm.

    Shape:
        The two broadcast; the result has the broadcast shape (NaN where both are 0).

    Returns:
        NDSI in [-1, 1]: high for skin (water absorbs at 1580 nm).

    >>> round(float(ndsi(0.53, 0.083)), 4)
    0.7292
    """
    nir = as_tensor(nir)
    return normalized_difference(nir, as_tensor(swir, like=nir))


def _band_index(bands: Sequence[Band], center: float, tol: float = 30.0) -> int:
    d = [abs(b.center_nm - center) for b in bands]
    i = min(range(len(d)), key=d.__getitem__)
    if d[i] > tol:
        raise ValueError(
            f"no band within {tol:g} nm of {center:g} nm among {[b.center_nm for b in bands]}: "
            f"the indices need bands near {', '.join(f'{c:g}' for c in INDEX_BANDS_NM[:-1])} and "
            f"{INDEX_BANDS_NM[-1]:g} nm"
        )
    return i


def has_index_bands(bands: Sequence[Band]) -> bool:
    """Whether ``bands`` hold one band within 30 nm of each of 544, 633, 1080 and 1580 nm (the indices' bands)."""
    try:
        for c in INDEX_BANDS_NM:
            _band_index(bands, c)
    except ValueError:
        return False
    return True


def index_band_positions(bands: Sequence[Band]) -> tuple[int, int, int, int]:
    """Positions in ``bands`` of the bands nearest (within 30 nm) to 544, 633, 1080 and 1580 nm; ``ValueError``
    if one has none."""
    g, r, n, s = (_band_index(bands, c) for c in INDEX_BANDS_NM)
    return g, r, n, s


def indices(reflectance: TensorLike, bands: Sequence[Band] | None = None,
            band_dim: int = -1) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ndgri, ndsi)`` of a reflectance tensor, from its bands nearest (within 30 nm) to ``INDEX_BANDS_NM``.

    Args:
        reflectance: band reflectance.
        bands: the bands along ``band_dim`` (default ``DEFAULT_BANDS``: 544, 633, 1080, 1580 nm in this order);
            ``ValueError`` if one of the four index bands has no band within 30 nm.
        band_dim: the band axis.

    Shape:
        ``reflectance`` ``(..., n_bands)`` (band axis ``band_dim``) gives two tensors of its shape without that
        axis.

    Returns:
        ``(ndgri, ndsi)``.

    >>> from torchskin import tissue
    >>> g, s = indices(tissue.reflectance(tissue.preset(["I-II", "V-VI"]), INDEX_BANDS_NM))
    >>> [round(x, 4) for x in g.tolist()], [round(x, 4) for x in s.tolist()]
    ([-0.3445, -0.386], [0.7294, 0.6986])
    """
    bands = as_bands(bands) if bands is not None else DEFAULT_BANDS
    reflectance = as_tensor(reflectance)
    if reflectance.shape[band_dim] != len(bands):
        raise ValueError(
            f"reflectance has {reflectance.shape[band_dim]} bands on axis {band_dim}, expected {len(bands)}"
        )
    g, r, n, s = (reflectance.select(band_dim, i) for i in index_band_positions(bands))
    return ndgri(g, r), ndsi(n, s)


@dataclass(frozen=True)
class RulesBox:
    """The rules detector's box: b1 <= NDGRI <= b2 and c1 <= NDSI <= c2 (eq 2.5.10)."""

    b1: float = -0.54079
    b2: float = -0.061525
    c1: float = 0.65703
    c2: float = 0.76779

    def __post_init__(self) -> None:
        if not (self.b1 <= self.b2 and self.c1 <= self.c2):
            raise ValueError(f"need b1 <= b2 and c1 <= c2, got {self}")

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


#: the thesis's diffuse-model box
DEFAULT_BOX = RulesBox()


def rules_detector(ndgri_: TensorLike, ndsi_: TensorLike, box: RulesBox | TensorLike = DEFAULT_BOX) -> torch.Tensor:
    """Boolean skin mask of the rules detector, eq 2.5.10: b1 <= NDGRI <= b2 and c1 <= NDSI <= c2.

    Args:
        ndgri_: NDGRI values (``ndgri``).
        ndsi_: NDSI values (``ndsi``), broadcasting with ``ndgri_``.
        box: a ``RulesBox`` (default: the thesis's ``DEFAULT_BOX``) or a tensor of (b1, b2, c1, c2) in its last
            axis, broadcasting with the indices (a per-pixel or per-configuration box).

    Shape:
        The indices broadcast (with a tensor box's ``(..., 4)`` leading axes); the mask has the broadcast shape.

    Returns:
        A bool mask; NaN indices are not skin.

    >>> rules_detector(torch.tensor([-0.3, 0.1]), torch.tensor([0.7, 0.7])).tolist()
    [True, False]
    """
    g = as_tensor(ndgri_)
    s = as_tensor(ndsi_, like=g)
    if isinstance(box, RulesBox):
        return (g >= box.b1) & (g <= box.b2) & (s >= box.c1) & (s <= box.c2)
    box = as_tensor(box, like=g)
    if box.shape[-1] != 4:
        raise ValueError(f"box tensor must end in 4 values (b1, b2, c1, c2), got shape {tuple(box.shape)}")
    b1, b2, c1, c2 = box.unbind(-1)
    return (g >= b1) & (g <= b2) & (s >= c1) & (s <= c2)


def histogram2d(x: TensorLike, y: TensorLike, bins: int = 64, range_x: tuple[float, float] = (-1.0, 1.0),
                range_y: tuple[float, float] = (-1.0, 1.0)) -> torch.Tensor:
    """Counts ``(bins, bins)`` of points (x, y) on a regular grid (device-agnostic: bucketize + bincount).

    Points outside the ranges or NaN are dropped.
    """
    x, y = as_tensor(x).reshape(-1), as_tensor(y).reshape(-1)
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same number of points, got {x.numel()} and {y.numel()}")
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    fx = (x - range_x[0]) / (range_x[1] - range_x[0]) * bins
    fy = (y - range_y[0]) / (range_y[1] - range_y[0]) * bins
    ok = (fx >= 0) & (fx <= bins) & (fy >= 0) & (fy <= bins)  # NaN compares False
    ix = fx.clamp(0, bins - 1).floor().long()
    iy = fy.clamp(0, bins - 1).floor().long()
    flat = torch.where(ok, ix * bins + iy, torch.zeros_like(ix))
    counts = torch.bincount(flat, weights=ok.to(x.dtype), minlength=bins * bins)
    return counts.reshape(bins, bins)


def bhattacharyya(h1: TensorLike, h2: TensorLike) -> torch.Tensor:
    """Bhattacharyya coefficient, eq 4.2.1: Σ √(p q) of two histograms, each normalised to sum 1.

    Histograms of any shape (1-D, 2-D NDSI x NDGRI, ...), summed over all bins. 1 for identical
    distributions, 0 for disjoint ones.
    """
    h1 = as_tensor(h1)
    h2 = as_tensor(h2, like=h1)
    if h1.shape != h2.shape:
        raise ValueError(f"histograms must have the same shape, got {tuple(h1.shape)} and {tuple(h2.shape)}")
    if bool((h1 < 0).any()) or bool((h2 < 0).any()):
        raise ValueError("histogram counts must be >= 0")
    s1, s2 = h1.sum(), h2.sum()
    if float(s1) == 0 or float(s2) == 0:
        raise ValueError("histograms must not be empty")
    return torch.sqrt((h1 / s1) * (h2 / s2)).sum()
