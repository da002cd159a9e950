"""The lookup-table head of ``OnboardDetector``: a ``lut``-kind ``detector.onnx`` (``torchskin.detectors.lut``)
computed per tile with numpy, the same operations in the same order as the graph, so that each pixel lands in
the same cell and gets the same decision.

Per frame the configuration picks one table slice, unpacked from the graph's bit table once and kept. Per tile
of n pixels, about forty passes over in-cache arrays: the tree's sums and normalized differences, the fourth
root of the band sum, the cell of each coordinate, one gather. numpy and onnx only (no torch)."""

from __future__ import annotations

import json

import numpy as np

from ..bands import band_tree


class LutHead:
    """The table of a ``lut`` graph (its ``lut_grid`` metadata and bit table) run per tile (``run``).

    Args:
        grid: the parsed ``lut_grid`` metadata: bins, n_bands, lo, inv, cfg_lo, cfg_inv, config_counts.
        bits: the graph's bit table (slices * cells / 8,) uint8, little-endian within a byte.
    """

    def __init__(self, grid: dict, bits: np.ndarray):
        self.n, self.bins = int(grid["n_bands"]), int(grid["bins"])
        self.lo = np.asarray(grid["lo"], dtype=np.float32)[:, None]
        self.inv = np.asarray(grid["inv"], dtype=np.float32)[:, None]
        self.cfg_lo = np.asarray(grid["cfg_lo"], dtype=np.float32)
        self.cfg_inv = np.asarray(grid["cfg_inv"], dtype=np.float32)
        self.counts = [int(c) for c in grid["config_counts"]]
        self.cells = self.bins ** self.n
        self.slices = int(np.prod(self.counts))
        if bits.size * 8 != self.slices * self.cells:
            raise ValueError(f"the lut table holds {bits.size * 8} bits for {self.slices} x {self.cells} cells")
        self.bits = bits.reshape(self.slices, self.cells // 8)
        self.tree = band_tree(self.n)
        self.strides = (self.bins ** np.arange(self.n - 1, -1, -1)).astype(np.float32)[:, None]
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
        """Slice ``s`` unpacked, one uint8 (0 or 1) per cell; made once and kept."""
        t = self._slices.get(s)
        if t is None:
            t = self._slices[s] = np.unpackbits(self.bits[s], bitorder="little")
        return t

    def scratch(self, n: int) -> dict[str, np.ndarray]:
        """A worker's buffers for tiles of ``n`` pixels."""
        return {"sums": np.empty((self.n - 1, n), dtype=np.float32), "u": np.empty((self.n, n), dtype=np.float32),
                "d": np.empty(n, dtype=np.float32), "idx": np.empty(n, dtype=np.float32),
                "cell": np.empty(n, dtype=np.int32)}

    def run(self, t: np.ndarray, table: np.ndarray, mask: np.ndarray, score: np.ndarray, sc: dict) -> None:
        """Mask and score (1 skin, 0 not) of a non-negative (n_bands, n) tile ``t`` under one slice's
        ``table``, into ``mask`` and ``score`` (n,), with the buffers ``sc`` (``scratch``)."""
        with np.errstate(invalid="ignore", divide="ignore"):  # 0 / 0: an undefined coordinate, ruled out below
            self._cells(t, sc)
        np.take(table, sc["cell"], out=mask.view(np.uint8), mode="clip")  # an undefined pixel's garbage cell: any
        idx = sc["idx"]
        if np.isnan(idx).any():  # an undefined coordinate (a bottom node's sum 0; rare): never skin
            mask[np.isnan(idx)] = False
        np.copyto(score, mask)  # 1 (skin) or 0

    def _cells(self, t: np.ndarray, sc: dict) -> None:
        """The cell of every pixel of the tile into ``sc["cell"]`` (``detectors.lut.grid.cells`` of
        ``coordinates``)."""
        u, d, sums = sc["u"], sc["d"], sc["sums"]
        node: dict[tuple[int, ...], np.ndarray] = {(i,): t[i] for i in range(self.n)}
        for k, (left, right) in enumerate(self.tree):  # each node: sum, difference, their ratio (the graph's order)
            a, b = node[left], node[right]
            s = node[left + right] = np.add(a, b, out=sums[k])
            np.subtract(a, b, out=d)
            np.divide(d, s, out=u[k])
        np.sqrt(node[tuple(range(self.n))], out=u[-1])
        np.sqrt(u[-1], out=u[-1])
        np.subtract(u, self.lo, out=u)
        np.multiply(u, self.inv, out=u)
        np.floor(u, out=u)
        np.clip(u, 0, self.bins - 1, out=u)  # NaN (an undefined coordinate) stays NaN: ruled out after the take
        np.multiply(u, self.strides, out=u)  # integers below 2 ** 24: exact in float32, in any order
        np.add.reduce(u, axis=0, out=sc["idx"])
        sc["cell"][...] = sc["idx"]  # NaN casts to a garbage index, clipped by the take


def lut_head(path: str, meta: dict) -> LutHead | None:
    """The ``LutHead`` of a ``lut`` graph at ``path`` (its ``lut_grid`` metadata and its one uint8 initializer, the
    bit table), or None without the ``onnx`` package or when either is missing: the graph then runs as it is."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        return None
    grid = meta.get("lut_grid")
    if not grid:
        return None
    m = onnx.load(path)
    tables = [t for t in m.graph.initializer if t.data_type == onnx.TensorProto.UINT8]
    if len(tables) != 1:
        return None
    return LutHead(json.loads(grid), numpy_helper.to_array(tables[0]))


__all__ = ["LutHead", "lut_head"]
