"""The ``lut`` kind's table geometry: where a pixel's spectrum and a frame's configuration fall in the table.

A float32 reflectance's bit pattern, read as an integer, is a piecewise-linear log2 of it: 2^23 units an octave,
exact at powers of two (``bits``). A pixel of n bands is placed by n integer coordinates of those logs:

- axis 0, the brightness: the bits of a reference band ``ref`` (chosen in training: the band the skin's log spreads
  least over; for the four index bands, 544 nm);
- axes 1 to n - 1: every other band's bits less those of its neighbour towards the reference, the log ratio of
  neighbouring bands (``ratio_pairs``). For the index bands with 544 nm the reference: 633 / 544 nm (NDGRI's ratio),
  1080 / 633 nm (near infrared against visible) and 1580 / 1080 nm (NDSI's).

Each axis is cut into ``bins`` cells of 2^shift units, from the cell ``lo`` (an integer): the cell of a
coordinate v is floor(v / 2^shift) - lo, clipped to [0, bins - 1]. Values outside fall in the edge cells, which are
never skin. A frame's configuration (sun zenith, camera zenith, relative azimuth, diffuse share) picks one table
slice, by equal bins over each feature's training domain.

Why bits: integer subtraction and a shift are exact on every backend, and the cheapest coordinates there are: no
division, no logarithm. Onboard a pixel costs a subtraction, a shift, a clip and a gather (``onboard.lut``).

A pixel with a band at 0 has no finite log ratio; its bits put it at least 2^23 units (an octave) from its
neighbour, in practice ~100 octaves for a lit neighbour, far outside any axis (``check_geometry``): it lands in an
edge cell. So do negative values and NaN. No pixel needs a separate test.

>>> R = torch.tensor([[0.5, 0.25, 1.0, 0.5]])
>>> coordinates(R, ref=3)  # 0.5 = 2^-1: bits 126 * 2^23; one octave between 0.5 and 0.25 is 2^23
tensor([[1056964608,    8388608,  -16777216,    8388608]])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ...bands import LUT_COORDINATES as COORDINATES  # the coordinates' name, kept in checkpoints
from ...bands import ratio_pairs

#: units of the coordinates per octave (a float32's mantissa bits)
OCTAVE = 1 << 23
#: the widest a ratio axis may reach from 0, in octaves (``check_geometry``): well inside the ~100 octaves between a
#: band at 0 and a lit neighbour, so that such a pixel always lands in an edge cell
RATIO_REACH_OCTAVES = 16


def bits(R: torch.Tensor) -> torch.Tensor:
    """The float32 bit patterns (..., n) int64 of reflectance ``R`` (cast to float32): a piecewise-linear log2,
    ``OCTAVE`` units an octave, 127 * ``OCTAVE`` at 1."""
    return R.float().contiguous().view(torch.int32).long()


def coordinates(R: torch.Tensor, ref: int = -1) -> torch.Tensor:
    """The n table coordinates (..., n) int64 of reflectance ``R`` (..., n): the reference band ``ref``'s bits (the
    brightness), then for every other band in order its bits less those of its neighbour towards ``ref`` (``ratio
    pairs``)."""
    return chain(bits(R), ref)


def chain(b: torch.Tensor, ref: int = -1, dim: int = -1) -> torch.Tensor:
    """``coordinates`` of bit patterns ``b`` whose bands lie along ``dim``: the reference band's, then each other
    band's less its neighbour's towards ``ref``, along ``dim``."""
    band, towards = ratio_pairs(b.shape[dim], ref)
    at = (slice(None),) * (dim % b.ndim)
    return torch.cat([b[at + (band[:1],)], b[at + (band[1:],)] - b[at + (towards[1:],)]], dim)


def cells(V: torch.Tensor, shift: torch.Tensor, lo: torch.Tensor, bins: int) -> torch.Tensor:
    """The flat cell index (...,) int64 of coordinates ``V`` (..., n) on ``bins`` cells per axis of 2^shift units
    from the cell ``lo`` (n,): per axis floor(v / 2^shift) - lo, clipped to [0, bins - 1], axis 0 slowest."""
    q = torch.bitwise_right_shift(V, shift.long().to(V.device))  # an arithmetic shift: the floor
    return flat_index(q, lo.long().to(V.device), bins)


def flat_index(q: torch.Tensor, lo: torch.Tensor, bins: int, dim: int = -1) -> torch.Tensor:
    """The flat cell index of per-axis cells ``q`` (axes along ``dim``; any integer-valued dtype, kept): each
    clipped to [lo, lo + bins - 1] (``lo`` broadcast against ``q``) less ``lo``, the first axis slowest."""
    q = torch.minimum(torch.maximum(q, lo), lo + (bins - 1)) - lo
    at = (slice(None),) * (dim % q.ndim)
    idx = q[at + (0,)]
    for k in range(1, q.shape[dim]):
        idx = idx * bins + q[at + (k,)]
    return idx


def axis_centres(q: torch.Tensor, shift: torch.Tensor, lo: torch.Tensor) -> torch.Tensor:
    """The coordinates (..., n) float64 of the centres of per-axis cells ``q`` (..., n) (integers in [0, bins))."""
    return (lo.double() + q.double() + 0.5) * _pow2(shift.long())


def cell_centres(shift: torch.Tensor, lo: torch.Tensor, bins: int) -> torch.Tensor:
    """The coordinates (bins ** n, n) float64 of every cell's centre, in flat index order (``cells``)."""
    n = len(lo)
    q = torch.stack(torch.meshgrid(*[torch.arange(bins)] * n, indexing="ij"), -1).reshape(-1, n)
    return axis_centres(q, shift, lo)


def from_bits(b: torch.Tensor) -> torch.Tensor:
    """The reflectance (float64) whose float32 bits are ``b`` (float64, fractional values between patterns: the
    piecewise-linear log2 read back), for b in [0, 255 * ``OCTAVE``)."""
    e = torch.floor(b / OCTAVE)
    frac = b / OCTAVE - e
    normal = _pow2((e - 127).clamp(-126, 127).long()) * (1 + frac)
    return torch.where(e >= 1, normal, b * 2.0 ** -149)  # below the normal range: subnormal, b * 2^-149


def _pow2(k: torch.Tensor) -> torch.Tensor:
    """2^k (float64) of integers k in [-1022, 1023], built from its bit pattern: exact on every CPU (a vectorized
    ``exp2`` need not be)."""
    return ((k + 1023) << 52).view(torch.float64)


def reflectance_of(V: torch.Tensor, ref: int = -1) -> torch.Tensor:
    """The reflectance (..., n) float64 whose coordinates are ``V`` (..., n) (float64 coordinates, ``coordinates``
    inverted: the reference band from its bits, each other band from its neighbour's towards the reference)."""
    n = V.shape[-1]
    band, towards = ratio_pairs(n, ref)
    b: list[torch.Tensor | None] = [None] * n
    b[band[0]] = V[..., 0]
    order = sorted(range(1, n), key=lambda k: abs(band[k] - band[0]))  # nearest the reference first
    for k in order:
        b[band[k]] = b[towards[k]] + V[..., k]  # type: ignore[operator]
    return from_bits(torch.stack(b, -1))  # type: ignore[arg-type]


def check_geometry(shift: Sequence[int], lo: Sequence[int], bins: int) -> None:
    """``ValueError`` unless every ratio axis (1 to n - 1) stays within ``RATIO_REACH_OCTAVES`` of 0 and the
    brightness axis starts above the subnormal range, so that a band at 0 always lands in an edge cell."""
    reach = RATIO_REACH_OCTAVES * OCTAVE
    for k, (s, a) in enumerate(zip(shift, lo, strict=True)):
        first, last = int(a) << int(s), (int(a) + bins) << int(s)
        if k == 0 and first < OCTAVE:
            raise ValueError(f"the brightness axis starts at {first} (below the normal floats)")
        if k > 0 and not -reach <= first < last <= reach:
            raise ValueError(f"ratio axis {k} spans [{first / OCTAVE:g}, {last / OCTAVE:g}] octaves, beyond "
                             f"+-{RATIO_REACH_OCTAVES}")


def config_bins(X: torch.Tensor, lo: torch.Tensor, inv: torch.Tensor, counts: Sequence[int]) -> torch.Tensor:
    """The table slice (...,) int64 of configurations ``X`` (..., k): per feature floor((x - lo) * inv) clipped
    to [0, count - 1], the first feature slowest."""
    idx = torch.zeros(X.shape[:-1], dtype=torch.long, device=X.device)
    for j, c in enumerate(counts):
        b = torch.floor((X[..., j] - lo[j]) * inv[j]).nan_to_num(0.0).clamp(0, c - 1).long()
        idx = idx * c + b
    return idx


__all__ = ["COORDINATES", "OCTAVE", "RATIO_REACH_OCTAVES", "axis_centres", "bits", "cell_centres", "cells",
           "chain", "check_geometry", "config_bins", "coordinates", "flat_index", "from_bits", "reflectance_of"]
