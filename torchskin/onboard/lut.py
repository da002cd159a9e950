"""The lookup-table head of ``OnboardDetector``: a ``lut``-kind ``detector.onnx`` (``torchskin.detectors.lut``)
computed per tile with numpy, the same operations in the same order as the graph, so that each pixel lands in
the same cell and gets the same decision.

Per frame the configuration picks one table slice, unpacked from the graph's bit table once and kept. Per tile
of n pixels, about twenty passes over in-cache arrays, most of them over all n coordinates at once: the tree's
sums and differences, one division for every coordinate, the cell of each coordinate, one gather. numpy and
onnx only (no torch)."""

from __future__ import annotations

import json

import numpy as np

from ..bands import BRIGHTNESS_REF_PER_BAND, band_tree
from ..bands import TREE_COORDINATES as COORDINATES


class LutHead:
    """The table of a ``lut`` graph (its ``lut_grid`` metadata and bit table) run per tile (``run``).

    Args:
        grid: the parsed ``lut_grid`` metadata: coordinates, bins, n_bands, lo, inv, cfg_lo, cfg_inv,
            config_counts. ``ValueError`` for a grid on other coordinates than this version's.
        bits: the graph's bit table (slices * cells / 8,) uint8, little-endian within a byte.
    """

    def __init__(self, grid: dict, bits: np.ndarray):
        if grid.get("coordinates") != COORDINATES:
            raise ValueError(f"the lut graph's coordinates are {grid.get('coordinates')!r}, not {COORDINATES!r}")
        self.n, self.bins = int(grid["n_bands"]), int(grid["bins"])
        self.lo = np.asarray(grid["lo"], dtype=np.float32)[:, None]
        self.inv = np.asarray(grid["inv"], dtype=np.float32)[:, None]
        self.cfg_lo = np.asarray(grid["cfg_lo"], dtype=np.float32)
        self.cfg_inv = np.asarray(grid["cfg_inv"], dtype=np.float32)
        self.counts = [int(c) for c in grid["config_counts"]]
        self.cells = self.bins ** self.n
        self.slices = int(np.prod(self.counts))
        if bits.size != -(-self.slices * self.cells // 8):
            raise ValueError(f"the lut table holds {bits.size * 8} bits for {self.slices} x {self.cells} cells")
        self.bits = bits.reshape(-1)  # one bit stream: a slice starts at bit s * cells (a byte's edge or not)
        self.ref = np.float32(BRIGHTNESS_REF_PER_BAND * self.n)
        self.top = np.float32(self.bins - 1)
        self.strides = (self.bins ** np.arange(self.n - 1, -1, -1)).astype(np.float32)
        self.plan = _tree_plan(band_tree(self.n), self.n)
        # every coordinate lies in [-1, 1] (non-negative bands): an axis whose cells cover that range with room to
        # spare needs no clip. The rows that do, as (first, last) runs of neighbours
        lo = self.lo[:, 0].astype(np.float64)
        need = ~((lo < -1) & ((1 - lo) * self.inv[:, 0] < self.bins - 0.01))
        rows = np.flatnonzero(need)
        runs = np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1)
        self.clip_rows = [(int(r[0]), int(r[-1]) + 1) for r in runs if len(r)]
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
            first = s * self.cells
            b0, b1 = first // 8, -(-(first + self.cells) // 8)
            bits = np.unpackbits(self.bits[b0:b1], bitorder="little")
            t = self._slices[s] = np.ascontiguousarray(bits[first - 8 * b0:first - 8 * b0 + self.cells])
        return t

    def scratch(self, n: int) -> dict[str, np.ndarray]:
        """A worker's buffers for tiles of ``n`` pixels: each coordinate's sum (denominator) and difference
        (numerator, then the coordinate, then its cell), and the flat cell index."""
        return {"S": np.empty((self.n, n), dtype=np.float32), "D": np.empty((self.n, n), dtype=np.float32),
                "cell": np.empty(n, dtype=np.int32)}

    def run(self, t: np.ndarray, table: np.ndarray, mask: np.ndarray, score: np.ndarray, sc: dict) -> None:
        """Mask and score (1 skin, 0 not) of a non-negative (n_bands, n) tile ``t`` under one slice's
        ``table``, into ``mask`` and ``score`` (n,), with the buffers ``sc`` (``scratch``)."""
        with np.errstate(invalid="ignore", divide="ignore"):  # 0 / 0: an undefined coordinate, ruled out below
            idx = self._cells(t, sc)
        np.take(table, sc["cell"], out=mask.view(np.uint8), mode="clip")  # an undefined pixel's garbage cell: any
        if np.isnan(np.min(idx)):  # an undefined coordinate (a bottom node's sum 0; rare): never skin
            mask[np.isnan(idx)] = False
        np.copyto(score, mask)  # 1 (skin) or 0

    def _cells(self, t: np.ndarray, sc: dict) -> np.ndarray:
        """The cell of every pixel of the tile into ``sc["cell"]`` (``detectors.lut.grid.cells`` of
        ``coordinates``); returns it as float32 (NaN for an undefined coordinate)."""
        S, D = sc["S"], sc["D"]
        src = {"t": t, "S": S}
        for first, last, (la, ls, lstep), (ra, rs, rstep) in self.plan:  # nodes first..last-1 in one call each
            a, b = src[la][ls:ls + lstep * (last - first):lstep], src[ra][rs:rs + rstep * (last - first):rstep]
            np.add(a, b, out=S[first:last])
            np.subtract(a, b, out=D[first:last])
        total = S[self.n - 2]  # the root's sum
        np.subtract(total, self.ref, out=D[-1])  # the brightness: (total - k) / (total + k)
        np.add(total, self.ref, out=S[-1])
        np.divide(D, S, out=D)  # every coordinate at once
        np.subtract(D, self.lo, out=D)
        np.multiply(D, self.inv, out=D)
        np.floor(D, out=D)
        for a, b in self.clip_rows:  # NaN (an undefined coordinate) stays NaN: ruled out after the take
            np.clip(D[a:b], 0, self.top, out=D[a:b])
        idx = S[0]
        np.einsum("k,kn->n", self.strides, D, out=idx)  # integers below 2 ** 24: exact in float32, in any order
        sc["cell"][...] = idx  # NaN casts to a garbage index, clipped by the take
        return idx


def _tree_plan(tree: list, n: int) -> list[tuple[int, int, tuple[str, int, int], tuple[str, int, int]]]:
    """The tree's nodes (``band_tree``) as runs of consecutive nodes whose left and right children each lie at
    a constant stride in one array: a band of the tile ("t", band) or an earlier node's sum ("S", node). Each run
    (first, last, (array, start, step) of the left children, the same of the right) is one add and one subtract
    over its rows: for four bands, NDGRI and NDSI together, then NDVN."""
    where = {(i,): ("t", i) for i in range(n)}
    where.update({left + right: ("S", k) for k, (left, right) in enumerate(tree)})
    runs: list[list] = []
    for k, (left, right) in enumerate(tree):
        a, b = where[left], where[right]
        if runs:
            first, last, (la, ls, lstep), (ra, rs, rstep) = runs[-1]
            count = last - first
            step_a, step_b = a[1] - ls, b[1] - rs
            fits = (a[0] == la and b[0] == ra and (count > 1 and step_a == lstep * count and step_b == rstep * count
                                                   or count == 1 and step_a > 0 and step_b > 0)
                    and not (a[0] == "S" and a[1] >= first) and not (b[0] == "S" and b[1] >= first))
            if fits:
                runs[-1] = [first, k + 1, (la, ls, step_a // count), (ra, rs, step_b // count)]
                continue
        runs.append([k, k + 1, (a[0], a[1], 1), (b[0], b[1], 1)])
    return [(f, last, tuple(la), tuple(rb)) for f, last, la, rb in runs]


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
    if json.loads(grid).get("coordinates") != COORDINATES:  # an earlier version's graph: run it as it is
        return None
    m = onnx.load(path)
    tables = [t for t in m.graph.initializer if t.data_type == onnx.TensorProto.UINT8]
    if len(tables) != 1:
        return None
    return LutHead(json.loads(grid), numpy_helper.to_array(tables[0]))


__all__ = ["LutHead", "lut_head"]
