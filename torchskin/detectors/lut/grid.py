"""The ``lut`` kind's table geometry: where a pixel's spectrum and a frame's configuration fall in the table.

A pixel of n bands is placed by n coordinates that describe its spectrum completely, each a share in [0, 1]:

- n - 1 shares, one per internal node of a balanced binary tree over the bands (``band_tree``): left sum /
  (left sum + right sum). For the four index bands they are (1 + NDGRI) / 2, (1 + NDSI) / 2 and (1 + NDVN) / 2,
  with NDVN = ((g + r) - (n + s)) / (g + r + n + s);
- the brightness: the band sum s against a reference ``k = n / 4`` (a mean reflectance of 0.25), s / (s + k). It
  resolves dark pixels finely and bright ones coarsely.

A share is one division of two sums, the cheapest exact coordinate: no subtraction, no root, no logarithm (not
correctly rounded on every backend).

Each axis is cut into ``bins`` equal cells of width ``1 / inv`` starting at ``lo``, a whole number of cells from 0
(``bands.grid_offsets``): the cell of a share u is floor(u * inv) - offset, clipped to [0, bins - 1]. Values outside
fall in the edge cells, which are never skin. A frame's configuration (sun zenith, camera zenith, relative azimuth)
picks one table slice, by equal bins over each feature's training domain. Every step is an IEEE-exact operation in a
fixed order (add, divide, multiply, floor), so torch, numpy and onnxruntime put a pixel in the same cell.

>>> R = torch.tensor([[0.3, 0.2, 0.5, 0.1]])
>>> coordinates(R).round(decimals=4)
tensor([[0.6000, 0.8333, 0.4545, 0.5238]])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ...bands import BRIGHTNESS_REF_PER_BAND, band_tree, grid_offsets
from ...bands import TREE_COORDINATES as COORDINATES  # the name of the coordinates below, kept in checkpoints


def coordinates(R: torch.Tensor) -> torch.Tensor:
    """The n table coordinates (..., n) of reflectance ``R`` (..., n): each tree node's left share (``band_tree``),
    then the brightness s / (s + k) of the band sum s (``brightness_ref``). NaN where a node's sum is 0
    (``valid``)."""
    n = R.shape[-1]
    sums: dict[tuple[int, ...], torch.Tensor] = {(i,): R[..., i] for i in range(n)}
    out = []
    for left, right in band_tree(n):
        a = sums[left]
        s = a + sums[right]
        sums[left + right] = s
        out.append(a / s)
    total = sums[tuple(range(n))]
    out.append(total / (total + brightness_ref(n)))
    return torch.stack(out, -1)


def brightness_ref(n: int) -> float:
    """The band sum k at which the brightness coordinate is 1/2: n / 4, a mean reflectance of 0.25 (exact in
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


def offsets(lo: torch.Tensor, inv: torch.Tensor) -> torch.Tensor:
    """Each axis's first cell in whole cells from 0 (``bands.grid_offsets``), (n,) float32."""
    return torch.tensor(grid_offsets(lo.tolist(), inv.tolist()), dtype=torch.float32)


def cells(U: torch.Tensor, lo: torch.Tensor, inv: torch.Tensor, bins: int, off: torch.Tensor | None = None
          ) -> torch.Tensor:
    """The flat cell index (...,) int64 of coordinates ``U`` (..., n) on ``bins`` cells per axis of width
    ``1 / inv`` from ``lo`` (a whole number of cells from 0, ``off``: ``offsets``, computed when not given): per
    axis floor(u * inv) - offset, clipped to [0, bins - 1], the first axis slowest. NaN coordinates land in cell 0
    of their axis (``valid`` rules such pixels out)."""
    off = (offsets(lo, inv) if off is None else off).to(U.dtype)
    q = torch.floor(U * inv.to(U.dtype)).nan_to_num(0.0)
    q = torch.minimum(torch.maximum(q, off), off + (bins - 1)) - off
    idx = q[..., 0].long()
    for k in range(1, q.shape[-1]):
        idx = idx * bins + q[..., k].long()
    return idx


def axis_centres(q: torch.Tensor, lo: torch.Tensor, inv: torch.Tensor) -> torch.Tensor:
    """The coordinates (..., n) float64 of the centres of per-axis cells ``q`` (..., n) (integers in [0, bins))."""
    return (offsets(lo, inv).double() + q.double() + 0.5) / inv.double()


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
    n = len(lo)
    q = torch.stack(torch.meshgrid(*[torch.arange(bins)] * n, indexing="ij"), -1).reshape(-1, n)
    return axis_centres(q, lo, inv)


def reflectance_of(U: torch.Tensor) -> torch.Tensor:
    """The reflectance (..., n) whose coordinates are ``U`` (..., n) (``coordinates`` inverted: the brightness
    splits down the tree by each node's share)."""
    n = U.shape[-1]
    b = U[..., -1]
    total = brightness_ref(n) * b / (1 - b)
    sums: dict[tuple[int, ...], torch.Tensor] = {tuple(range(n)): total}
    for k, (left, right) in reversed(list(enumerate(band_tree(n)))):
        s = sums[left + right]
        sums[left] = s * U[..., k]
        sums[right] = s * (1 - U[..., k])
    return torch.stack([sums[(i,)] for i in range(n)], -1)


__all__ = ["COORDINATES", "axis_centres", "brightness_ref", "cell_centres", "cells", "config_bins", "coordinates", "offsets", "reflectance_of", "valid"]
