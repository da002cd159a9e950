"""The lookup-table head of ``OnboardDetector``: a ``lut``-kind ``detector.onnx`` (``torchskin.detectors.lut``)
computed per tile with numpy. It reads each band's float32 bits as integers, as the torch model does, so every pixel
lands in the cell torch and the graph give it.

Per frame the configuration picks one table slice, unpacked from the graph's bit table once and kept. Per tile of
n pixels, five passes over in-cache integer arrays: the log ratios (one or two subtractions), the cells (one shift
and one clip over every axis), the flat index (one ``einsum``), one gather. numpy and onnx only (no torch)."""

from __future__ import annotations

import functools
import json
import os

import numpy as np

from ..bands import LUT_COORDINATES as COORDINATES
from ..bands import ratio_pairs

#: the largest table index (offsets included) the head sums in int32
_INT32 = (1 << 31) - 1


class LutHead:
    """The table of a ``lut`` graph (its ``lut_grid`` metadata and bit table) run per tile (``run``).

    Args:
        grid: the parsed ``lut_grid`` metadata: coordinates, bins, n_bands, ref, shift, lo, cfg_lo, cfg_inv,
            config_counts. ``ValueError`` for a grid on other coordinates than this version's.
        bits: the graph's bit table (slices * cells / 8,) uint8, little-endian within a byte.
    """

    def __init__(self, grid: dict, bits: np.ndarray):
        if grid.get("coordinates") != COORDINATES:
            raise ValueError(f"the lut graph's coordinates are {grid.get('coordinates')!r}, not {COORDINATES!r}")
        self.n, self.bins, self.ref = int(grid["n_bands"]), int(grid["bins"]), int(grid["ref"]) % int(grid["n_bands"])
        band, _ = ratio_pairs(self.n, self.ref)
        self.cfg_lo = np.asarray(grid["cfg_lo"], dtype=np.float32)
        self.cfg_inv = np.asarray(grid["cfg_inv"], dtype=np.float32)
        self.counts = [int(c) for c in grid["config_counts"]]
        self.cells = self.bins ** self.n
        self.slices = int(np.prod(self.counts))
        if bits.size != -(-self.slices * self.cells // 8):
            raise ValueError(f"the lut table holds {bits.size * 8} bits for {self.slices} x {self.cells} cells")
        self.bits = bits.reshape(-1)  # one bit stream: a slice starts at bit s * cells (a byte's edge or not)
        # per band row (the tile's order): its axis's shift, first and last cell, stride in the flat index
        order = np.argsort(band)  # band i's axis
        shift, lo = np.asarray(grid["shift"], np.int64)[order], np.asarray(grid["lo"], np.int64)[order]
        strides = (self.bins ** (self.n - 1 - np.arange(self.n)))[order]
        self.shift = shift.astype(np.int32)[:, None]
        self.lo, self.hi = lo.astype(np.int32)[:, None], (lo + self.bins - 1).astype(np.int32)[:, None]
        self.strides = strides.astype(np.int32)
        # each axis's cell plus its offset is summed as it is: the table is read from ``base`` zero cells on, so no
        # pass subtracts the offsets (unless the sum would leave int32: then they are subtracted)
        self.base = int((strides * lo).sum())
        self.offset_free = 0 <= self.base and self.base + self.cells <= _INT32
        if not self.offset_free:
            self.base = 0
        self._slices: dict[int, np.ndarray] = {}

    def slice_of(self, config: np.ndarray) -> int:
        """The table slice of one configuration (k,): per feature floor((x - lo) * inv) in float32, clipped to
        [0, count - 1], the first feature slowest (``detectors.lut.grid.config_bins``)."""
        x = np.asarray(config, dtype=np.float32)
        q = np.floor((x - self.cfg_lo) * self.cfg_inv)
        idx = 0
        for j, c in enumerate(self.counts):
            b = 0 if not np.isfinite(q[j]) else int(min(max(q[j], 0), c - 1))
            idx = idx * c + b
        return idx

    def table(self, s: int) -> np.ndarray:
        """Slice ``s`` unpacked, one uint8 (0 or 1) per cell after ``base`` zero cells; made once and kept."""
        t = self._slices.get(s)
        if t is None:
            first = s * self.cells
            b0, b1 = first // 8, -(-(first + self.cells) // 8)
            bits = np.unpackbits(self.bits[b0:b1], bitorder="little")
            t = np.zeros(self.base + self.cells, dtype=np.uint8)  # the zero cells: pages never written or read
            t[self.base:] = bits[first - 8 * b0:first - 8 * b0 + self.cells]
            self._slices[s] = t
        return t

    def scratch(self, n: int) -> dict[str, np.ndarray]:
        """A worker's buffers for tiles of ``n`` pixels: each axis's coordinate and cell (int32, in band order) and
        the table index."""
        return {"D": np.empty((self.n, n), dtype=np.int32), "cell": np.empty(n, dtype=np.int32)}

    def run(self, t: np.ndarray, table: np.ndarray, mask: np.ndarray, score: np.ndarray, sc: dict) -> None:
        """Mask and score (1 skin, 0 not) of a (n_bands, n) float32 tile ``t`` under one slice's ``table``, into
        ``mask`` and ``score`` (n,), with the buffers ``sc`` (``scratch``)."""
        self._cells(t, sc)
        np.take(table, sc["cell"], out=mask.view(np.uint8), mode="clip")
        np.copyto(score, mask)  # 1 (skin) or 0

    def _cells(self, t: np.ndarray, sc: dict) -> None:
        """The table index (``base`` + cell, ``detectors.lut.grid.cells`` of ``coordinates``) of every pixel of
        the tile into ``sc["cell"]``."""
        D, r, n = sc["D"], self.ref, self.n
        T = t.view(np.int32)  # the bits: a piecewise-linear log2
        if r > 0:  # bands before the reference: less their right neighbour
            np.subtract(T[:r], T[1:r + 1], out=D[:r])
        if r < n - 1:  # bands after it: less their left neighbour
            np.subtract(T[r + 1:], T[r:n - 1], out=D[r + 1:])
        np.copyto(D[r], T[r])  # the brightness
        np.right_shift(D, self.shift, out=D)  # an arithmetic shift: the floor
        np.clip(D, self.lo, self.hi, out=D)
        if not self.offset_free:
            np.subtract(D, self.lo, out=D)
        np.einsum("k,kn->n", self.strides, D, out=sc["cell"])


def lut_head(path: str, meta: dict) -> LutHead | None:
    """The ``LutHead`` of a ``lut`` graph at ``path`` (its ``lut_grid`` metadata and its one uint8 initializer, the
    bit table), or None without the ``onnx`` package or when either is missing: the graph then runs as it is.
    Detectors of one unchanged file share one head (its slices unpacked once): reading the 38 MB graph again
    costs ~0.07 s a detector."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return _cached_head(os.path.abspath(path), st.st_mtime_ns, st.st_size, meta.get("lut_grid") or "")


@functools.lru_cache(maxsize=4)
def _cached_head(path: str, mtime_ns: int, size: int, grid: str) -> LutHead | None:
    """``lut_head`` of one version of a file (its path, modification time and size) and its grid metadata."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        return None
    if not grid:
        return None
    if json.loads(grid).get("coordinates") != COORDINATES:  # an earlier version's graph: run it as it is
        return None
    m = onnx.load(path)
    tables = [t for t in m.graph.initializer if t.data_type == onnx.TensorProto.UINT8]
    if len(tables) != 1:
        return None
    return LutHead(json.loads(grid), numpy_helper.to_array(tables[0]))


__all__ = ["LutHead", "lut_head"]
