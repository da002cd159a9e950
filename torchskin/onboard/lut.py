"""The lookup-table head of ``OnboardDetector``: a ``lut``-kind ``detector.onnx`` (``torchskin.detectors.lut``)
computed per tile with numpy, the same operations in the same order as the graph, so that each pixel lands in
the same cell and gets the same decision.

Per frame the configuration picks one table slice, unpacked from the graph's bit table once and kept. Per tile
of n pixels, about a dozen passes over in-cache arrays, most of them over all n coordinates at once: the tree's
sums, one division per coordinate, the cell of each coordinate, one gather. numpy and onnx only (no torch)."""

from __future__ import annotations

import json

import numpy as np

from ..bands import BRIGHTNESS_REF_PER_BAND, band_tree, grid_offsets
from ..bands import TREE_COORDINATES as COORDINATES

#: the largest table index (offsets included) the head sums in int32
_INT32 = (1 << 31) - 1


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
        self.inv = np.asarray(grid["inv"], dtype=np.float32)[:, None]
        off = np.array(grid_offsets(grid["lo"], grid["inv"]), dtype=np.float64)
        self.cfg_lo = np.asarray(grid["cfg_lo"], dtype=np.float32)
        self.cfg_inv = np.asarray(grid["cfg_inv"], dtype=np.float32)
        self.counts = [int(c) for c in grid["config_counts"]]
        self.cells = self.bins ** self.n
        self.slices = int(np.prod(self.counts))
        if bits.size != -(-self.slices * self.cells // 8):
            raise ValueError(f"the lut table holds {bits.size * 8} bits for {self.slices} x {self.cells} cells")
        self.bits = bits.reshape(-1)  # one bit stream: a slice starts at bit s * cells (a byte's edge or not)
        self.ref = np.float32(BRIGHTNESS_REF_PER_BAND * self.n)
        strides = self.bins ** np.arange(self.n - 1, -1, -1)
        self.strides = strides.astype(np.int32)
        # each axis's cell plus its offset is summed as it is: the table is read from ``base`` zero cells on, so no
        # pass subtracts the offsets (unless the sum would leave int32: then they are subtracted)
        self.base = int((strides * off).sum())
        self.offset_free = 0 <= self.base and self.base + self.cells <= _INT32
        if not self.offset_free:
            self.base = 0
        self.off_lo = off.astype(np.int32)[:, None]
        self.off_hi = (off + self.bins - 1).astype(np.int32)[:, None]
        self.sum_plan, self.div_plan = _tree_plans(band_tree(self.n), self.n)
        # every tree axis is clipped: an undefined share (0 / 0, NaN) casts to an integer (INT_MIN on x86-64, 0 on
        # ARM), which the clip puts in one cell of the axis, ``landing``: the first, an edge cell, unless the axis
        # starts below 0 and NaN casts to 0. The brightness is never undefined; it lies in [0, 1], so
        # floor(u * inv) in [0, floor(inv)]: from at most 0 with room up to 1 it needs no clip either
        bright_free = off[-1] <= 0 and float(self.inv[-1, 0]) < off[-1] + self.bins
        self.clip_rows = self.n - 1 if bright_free else self.n
        with np.errstate(invalid="ignore"):
            nan = np.full(1, np.nan, dtype=np.float32).astype(np.int32)[0]
        self.landing = [int(np.clip(nan, lo_k, lo_k + self.bins - 1) - lo_k) for lo_k in off[:-1].astype(np.int64)]
        self._slices: dict[int, np.ndarray] = {}
        self._edge_free: dict[int, bool] = {}  # per slice: no tree axis's landing cell holds skin

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
            grid = t[self.base:].reshape((self.bins,) * self.n)
            # where an undefined pixel lands: a tree axis's landing cell (its first, never skin in a trained
            # table, on x86-64). Kept before the slice, which another worker may read at once
            self._edge_free[s] = not any(grid.take(c, axis=k).any() for k, c in enumerate(self.landing))
            self._slices[s] = t
        return t

    def scratch(self, n: int) -> dict[str, np.ndarray]:
        """A worker's buffers for tiles of ``n`` pixels: each node's sum (and the brightness denominator), each
        coordinate, each axis's cell, and the table index."""
        return {"S": np.empty((self.n, n), dtype=np.float32), "U": np.empty((self.n, n), dtype=np.float32),
                "Q": np.empty((self.n, n), dtype=np.int32), "cell": np.empty(n, dtype=np.int32)}

    def run(self, t: np.ndarray, table: np.ndarray, mask: np.ndarray, score: np.ndarray, sc: dict,
            edge_free: bool = True) -> None:
        """Mask and score (1 skin, 0 not) of a non-negative (n_bands, n) tile ``t`` under one slice's
        ``table``, into ``mask`` and ``score`` (n,), with the buffers ``sc`` (``scratch``). ``edge_free``: the
        slice holds no skin in any tree axis's ``landing`` cell (``edge_free``), where an undefined pixel lands;
        otherwise such pixels are found and ruled out."""
        with np.errstate(invalid="ignore", divide="ignore"):  # 0 / 0: an undefined coordinate, ruled out below
            self._cells(t, sc)
        np.take(table, sc["cell"], out=mask.view(np.uint8), mode="clip")
        if not edge_free:
            S = sc["S"][: self.n - 1]  # an undefined pixel: a node's sum 0 (non-negative bands)
            if not S.min() > 0:
                mask[~(S > 0).all(0)] = False
        np.copyto(score, mask)  # 1 (skin) or 0

    def edge_free(self, s: int) -> bool:
        """Whether slice ``s`` holds no skin in any tree axis's ``landing`` cell (``table``)."""
        self.table(s)
        return self._edge_free[s]

    def _cells(self, t: np.ndarray, sc: dict) -> None:
        """The table index (``base`` + cell, ``detectors.lut.grid.cells`` of ``coordinates``) of every pixel of
        the tile into ``sc["cell"]`` (an undefined pixel's: a cell on a tree axis's ``landing`` cell)."""
        S, U, Q = sc["S"], sc["U"], sc["Q"]
        src = {"t": t, "S": S}
        for first, last, (la, ls, lstep), (ra, rs, rstep) in self.sum_plan:  # nodes first..last-1, one call each
            np.add(src[la][ls:ls + lstep * (last - first):lstep], src[ra][rs:rs + rstep * (last - first):rstep],
                   out=S[first:last])
        np.add(S[self.n - 2], self.ref, out=S[-1])  # the brightness: total / (total + k)
        for first, last, (na, ns, nstep) in self.div_plan:  # each coordinate: its left sum / its sum
            np.divide(src[na][ns:ns + nstep * (last - first):nstep], S[first:last], out=U[first:last])
        np.multiply(U, self.inv, out=U)
        np.copyto(Q, U, casting="unsafe")  # truncation: the floor of a value >= 0 (NaN: INT_MIN, or 0 on ARM)
        c = self.clip_rows
        np.clip(Q[:c], self.off_lo[:c], self.off_hi[:c], out=Q[:c])
        if not self.offset_free:
            np.subtract(Q, self.off_lo, out=Q)
        np.einsum("k,kn->n", self.strides, Q, out=sc["cell"])


def _tree_plans(tree: list, n: int) -> tuple[list, list]:
    """The tree's nodes (``band_tree``) as calls. Sums: runs of consecutive nodes whose left and right children
    each lie at a constant stride in one array, a band of the tile ("t", band) or an earlier node's sum ("S",
    node): (first, last, (array, start, step) of the left children, the same of the right), one add each (for four
    bands the two bottom pairs together, then the root). Divisions: runs of consecutive coordinates (the nodes, then
    the brightness, whose numerator is the root's sum) whose numerators lie at a constant stride in one array:
    (first, last, (array, start, step)), each divided by its row of sums (for four bands two calls)."""
    where = {(i,): ("t", i) for i in range(n)}
    where.update({left + right: ("S", k) for k, (left, right) in enumerate(tree)})
    sums: list[list] = []
    for k, (left, right) in enumerate(tree):
        a, b = where[left], where[right]
        if sums:
            first, last, (la, ls, lstep), (ra, rs, rstep) = sums[-1]
            if _extends((la, ls, lstep), a, last - first, first) and _extends((ra, rs, rstep), b, last - first, first):
                count = last - first
                sums[-1] = [first, k + 1, (la, ls, (a[1] - ls) // count), (ra, rs, (b[1] - rs) // count)]
                continue
        sums.append([k, k + 1, (a[0], a[1], 1), (b[0], b[1], 1)])
    numerators = [where[left] for left, _ in tree] + [("S", n - 2)]
    divs: list[list] = []
    for k, a in enumerate(numerators):
        if divs:
            first, last, (na, ns, nstep) = divs[-1]
            if _extends((na, ns, nstep), a, last - first, None):
                divs[-1] = [first, k + 1, (na, ns, (a[1] - ns) // (last - first))]
                continue
        divs.append([k, k + 1, (a[0], a[1], 1)])
    return ([(f, last, tuple(la), tuple(rb)) for f, last, la, rb in sums],
            [(f, last, tuple(na)) for f, last, na in divs])


def _extends(run: tuple[str, int, int], at: tuple[str, int], count: int, first: int | None) -> bool:
    """Whether the array position ``at`` continues a run of ``count`` positions (array, start, step) at its stride
    (a run of one takes any positive stride), and, for sums (``first``: the run's first node), is not a sum the run
    itself writes."""
    arr, start, step = run
    if at[0] != arr:
        return False
    gap = at[1] - start
    fits = gap == step * count if count > 1 else gap > 0
    return fits and not (first is not None and arr == "S" and at[1] >= first)


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
