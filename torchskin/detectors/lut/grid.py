"""The ``lut`` kind's table geometry: where a pixel's spectrum and a frame's configuration fall in the table.

A pixel of n bands is placed by n coordinates that describe its spectrum completely:

- n - 1 normalized differences, one per internal node of a balanced binary tree over the bands (``band_tree``):
  (left sum - right sum) / (left sum + right sum). For the four index bands (g, r, n, s) they are NDGRI, NDSI and
  NDVN = ((g + r) - (n + s)) / (g + r + n + s);
- the brightness: the normalized difference of the band sum s against a reference ``k = n / 4`` (a mean
  reflectance of 0.25), (s - k) / (s + k). It spans (-1, 1) like the others, resolves dark pixels finely and
  bright ones coarsely, and costs one add, one subtract and one divide (a root or a logarithm costs more per
  pixel onboard, and a logarithm is not correctly rounded on every backend).

Each coordinate is cut into ``bins`` equal cells over its range [lo, hi); values outside fall in the edge cells. A
frame's configuration (sun zenith, camera zenith, relative azimuth) picks one table slice, by equal bins over
each feature's training domain. Every step is an IEEE-exact operation in a fixed order (add, subtract, divide,
multiply, floor), so torch, numpy and onnxruntime put a pixel in the same cell.

>>> R = torch.tensor([[0.3, 0.2, 0.5, 0.1]])
>>> coordinates(R).round(decimals=4)
tensor([[ 0.2000,  0.6667, -0.0909,  0.0476]])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ...bands import BRIGHTNESS_REF_PER_BAND, band_tree
from ...bands import TREE_COORDINATES as COORDINATES  # the name of the coordinates below, kept in checkpoints


def coordinates(R: torch.Tensor) -> torch.Tensor:
    """The n table coordinates (..., n) of reflectance ``R`` (..., n): the tree's normalized differences
    (``band_tree``), then the brightness (s - k) / (s + k) of the band sum s (``brightness_ref``). NaN where a
    node's sum is 0 (``valid``)."""
    n = R.shape[-1]
    sums: dict[tuple[int, ...], torch.Tensor] = {(i,): R[..., i] for i in range(n)}
    out = []
    for left, right in band_tree(n):
        a, b = sums[left], sums[right]
        s = a + b
        sums[left + right] = s
        out.append((a - b) / s)
    total, k = sums[tuple(range(n))], brightness_ref(n)
    out.append((total - k) / (total + k))
    return torch.stack(out, -1)


def brightness_ref(n: int) -> float:
    """The band sum k at which the brightness coordinate is 0: n / 4, a mean reflectance of 0.25 (exact in
    float32)."""
    return BRIGHTNESS_REF_PER_BAND * n


def valid(R: torch.Tensor) -> torch.Tensor:
    """Pixels (...,) whose every tree node has a positive band sum: the others have no defined coordinates and are
    never skin. For non-negative reflectance this is: every bottom pair of the tree sums above 0."""
    n = R.shape[-1]
    ok = torch.ones(R.shape[:-1], dtype=torch.bool, device=R.device)
    for left, right in band_tree(n):
        ok = ok & (R[..., list(left + right)].sum(-1) > 0)
    return ok


def cells(U: torch.Tensor, lo: torch.Tensor, inv: torch.Tensor, bins: int) -> torch.Tensor:
    """The flat cell index (...,) int64 of coordinates ``U`` (..., n) on ``bins`` cells per axis over
    [lo, lo + bins / inv): per axis floor((u - lo) * inv), clipped to [0, bins - 1], the first axis slowest. NaN
    coordinates land in cell 0 of their axis (``valid`` rules such pixels out)."""
    q = torch.floor((U - lo) * inv).nan_to_num(0.0).clamp(0, bins - 1).long()
    idx = q[..., 0]
    for k in range(1, q.shape[-1]):
        idx = idx * bins + q[..., k]
    return idx


def config_bins(X: torch.Tensor, lo: torch.Tensor, inv: torch.Tensor, counts: Sequence[int]) -> torch.Tensor:
    """The table slice (...,) int64 of configurations ``X`` (..., k): per feature floor((x - lo) * inv) clipped
    to [0, count - 1], the first feature slowest."""
    idx = torch.zeros(X.shape[:-1], dtype=torch.long, device=X.device)
    for j, c in enumerate(counts):
        b = torch.floor((X[..., j] - lo[j]) * inv[j]).nan_to_num(0.0).clamp(0, c - 1).long()
        idx = idx * c + b
    return idx


def cell_centres(lo: torch.Tensor, inv: torch.Tensor, bins: int) -> torch.Tensor:
    """The coordinates (bins ** n, n) float64 of every cell's centre, in flat index order (``cells``)."""
    axes = [lo[k].double() + (torch.arange(bins, dtype=torch.float64) + 0.5) / inv[k].double()
            for k in range(len(lo))]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(lo))


def reflectance_of(U: torch.Tensor) -> torch.Tensor:
    """The reflectance (..., n) whose coordinates are ``U`` (..., n) (``coordinates`` inverted: the brightness
    splits down the tree by each node's normalized difference)."""
    n = U.shape[-1]
    b = U[..., -1]
    total = brightness_ref(n) * (1 + b) / (1 - b)
    sums: dict[tuple[int, ...], torch.Tensor] = {tuple(range(n)): total}
    for k, (left, right) in reversed(list(enumerate(band_tree(n)))):
        s = sums[left + right]
        sums[left] = s * (1 + U[..., k]) / 2
        sums[right] = s * (1 - U[..., k]) / 2
    return torch.stack([sums[(i,)] for i in range(n)], -1)


__all__ = ["COORDINATES", "brightness_ref", "cell_centres", "cells", "config_bins", "coordinates", "reflectance_of", "valid"]
