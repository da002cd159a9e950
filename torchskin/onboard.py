"""Onboard runtime: load the exported ONNX models and run them with numpy and onnxruntime only (no torch).

    det = OnboardDetector("exports/detector.onnx")
    out = det(cube, config)      # cube (B, 4, H, W) float32 reflectance, config (B, k) in the model's units
    out["mask"], out["score"], out["out_of_domain"]

``score`` is the smallest margin to a box edge in index units weighted by the band-pair sum (positive inside;
see ``torchskin.detectors.boxes.BoxDetector``).

Inputs are validated: wrong rank, band count or dtype, NaN or negative reflectance, and values far outside
[0, 1.2] (below ``REFLECTANCE_MIN``, above ``REFLECTANCE_MAX`` in more than ``REFLECTANCE_MAX_SHARE`` of the
values: digital numbers, per cent; a glint is allowed; or any value above ``REFLECTANCE_CEILING``, which no camera
records) raise ``ValueError``;
float64, float16 and big-endian cubes are converted to float32 (``io.as_float32``);
configurations outside the training domain are flagged per frame in ``out_of_domain`` (never silently used).
Calibrated frames of dark pixels (sky, deep shadow) carry slightly negative reflectance from sensor noise:
``det(cube, config, negative="clip")`` sets those values to 0 instead and counts them per frame in
``clipped_values`` (a pixel whose band pairs sum to 0 is never skin).

The ELM of camera frames (``panel_signal``, ``elm_fit``, ``elm_apply``) is numpy too; the command line
(``torchskin detect``, ``torchskin calibrate``) is ``torchskin.cli.detect`` and ``torchskin.cli.calibrate``.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import ArrayLike

from .bands import BAND_MATCH_NM, BandSet  # how far a cube's band centre may lie from the model's
from .io import MAX_MEGAPIXELS, StrPath, as_float32

if TYPE_CHECKING:
    from concurrent.futures import ThreadPoolExecutor

#: reflectance above this in more than ``REFLECTANCE_MAX_SHARE`` of a cube's values is not calibrated reflectance:
#: the detector refuses the cube. The ELM maps the white panel (0.97-0.99) near the top of the sensor's range; a
#: calibrated frame reads more only where a surface receives more light than the panels (a surface facing a low
#: sun that grazes level panels: ``render.elm.panel_irradiance_ratio`` times its reflectance) or in a specular
#: glint (water, glass, a car), which is why a few such values are allowed. Digital numbers (up to 2^bits) and per cent (up to 100) put
#: nearly every value above it
REFLECTANCE_MAX = 1.5
#: the share of a cube's values that may read above ``REFLECTANCE_MAX`` (glints, sun-facing surfaces), each at
#: most ``REFLECTANCE_CEILING``
REFLECTANCE_MAX_SHARE = 0.01
#: no value of a calibrated cube, glint or not, reads above this: reflectance is (signal - offset) / gain after
#: the empirical line, whose white panel (0.97-0.99) sits between the sensor's full scale and 1/16 of it (the range
#: of the sensor model: ``REFLECTANCE_MIN``, ``render.elm.panel_median_noise_dn``), so a saturated pixel, the most
#: light a camera records, reads at most about 16 x 0.99 = 16; 50 leaves a factor 3 (a panel set darker still, an
#: offset below 0). A value above it is not light but a corrupt or fill value (1e30, 65535) or a digital number:
#: refused whatever its share
REFLECTANCE_CEILING = 50.0
#: reflectance below this anywhere in a frame is refused too: the ELM's noise on a black pixel is σ_DN / gain, about
#: 1e-4 with the white panel near full scale and 1e-3 with it at 1/16 of it (read noise 20-80 e-, 14-bit ADC:
#: ``render.elm.panel_median_noise_dn``), so -0.2 is hundreds of σ away: an offset or a line that is wrong, not noise
#: (``negative="clip"`` clips only values above this)
REFLECTANCE_MIN = -0.2


#: the shipped detector, packaged with torchskin (a copy of the repository's ``exports/detector.onnx``, made by
#: ``make demo``'s export step): ``torchskin detect``'s and ``OnboardDetector``'s default model
SHIPPED_DETECTOR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "detector.onnx")


def match_bands(cube_bands: Sequence[float], model_bands: Sequence[float], tol_nm: float = BAND_MATCH_NM) -> list[int]:
    """For each of the model's bands, the index of the cube's band at that wavelength (within ``tol_nm``): the
    order to read the cube in. ``ValueError`` naming the band when the cube has none there.

    >>> match_bands([1580, 544, 1080, 633], [544, 633, 1080, 1580])
    [1, 3, 2, 0]
    >>> match_bands([544, 633, 1080], [544, 633, 1080, 1580])
    Traceback (most recent call last):
    ...
    ValueError: the cube's bands (544, 633, 1080 nm) do not include the model's 1580 nm band (within 2 nm)
    """
    cube = np.asarray(cube_bands, dtype=np.float64)
    order = []
    for b in model_bands:
        d = np.abs(cube - float(b))
        if not d.size or d.min() > tol_nm:
            raise ValueError(f"the cube's bands ({', '.join(f'{v:g}' for v in cube)} nm) do not include the model's "
                             f"{float(b):g} nm band (within {tol_nm:g} nm)")
        order.append(int(d.argmin()))
    return order


def check_reflectance_range(low: float, high: float, above: float = 1.0, where: str = "cube") -> None:
    """``ValueError`` with a hint when a cube's reflectance lies out of meaning: its smallest value ``low`` below
    ``REFLECTANCE_MIN``, its largest ``high`` above ``REFLECTANCE_MAX`` in more than ``REFLECTANCE_MAX_SHARE``
    of its values (``above``: that share; 1 when not counted), or ``high`` above ``REFLECTANCE_CEILING`` at all
    (one value is enough: no camera records it). Values far outside [0, 1.2] are not calibrated reflectance.
    ``where`` names the cube in the message (a file: ``--cube 'x.npy'``).

    >>> check_reflectance_range(0.0, 4.0, above=0.0005)  # a glint: fine
    >>> check_reflectance_range(0.0, 49.0, above=0.0005)  # brighter than a glint, but a camera could record it
    >>> check_reflectance_range(0.0, 97.0, above=0.9)
    Traceback (most recent call last):
    ...
    ValueError: cube reads reflectance above 1.5 in 90.0 % of its values (up to 97; refused above 1 %): is this uncalibrated signal (digital numbers; torchskin calibrate converts it)? per cent (divide by 100)?
    >>> check_reflectance_range(0.0, 1e30, above=0.0001, where="--cube 'c.npy'")
    Traceback (most recent call last):
    ...
    ValueError: --cube 'c.npy' reads reflectance 1e+30, which no camera records (refused above 50: a saturated pixel reads at most about 16 times the white panel's reflectance): a corrupt or fill value, or uncalibrated signal?
    """
    if high > REFLECTANCE_MAX and above > REFLECTANCE_MAX_SHARE:
        raise ValueError(f"{where} reads reflectance above {REFLECTANCE_MAX:g} in {100 * above:.1f} % of its values "
                         f"(up to {high:.4g}; refused above {100 * REFLECTANCE_MAX_SHARE:g} %): is this uncalibrated "
                         "signal (digital numbers; torchskin calibrate converts it)? per cent (divide by 100)?")
    if high > REFLECTANCE_CEILING:
        raise ValueError(f"{where} reads reflectance {high:.4g}, which no camera records (refused above "
                         f"{REFLECTANCE_CEILING:g}: a saturated pixel reads at most about 16 times the white panel's "
                         "reflectance): a corrupt or fill value, or uncalibrated signal?")
    if low < np.float32(REFLECTANCE_MIN):  # cubes are float32: -0.2 as a float32 is at the bound, not below it
        raise ValueError(f"{where} reads reflectance down to {low:.4g}, far below 0 (refused below "
                         f"{REFLECTANCE_MIN:g}; sensor noise reaches about -0.001): is this uncalibrated signal "
                         "with an offset, or calibrated with swapped panels?")


class _Model:
    KIND = "torchskin"
    IO: tuple[set, set] = (set(), set())

    def __init__(self, path: str | os.PathLike, threads: int | None = None):
        import onnxruntime as ort

        self.path = str(path)
        self.threads = max(1, int(threads or min(os.cpu_count() or 1, 8)))
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1  # frames are split into tiles that run on ``threads`` workers instead
        so.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(self.path, so, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types
            raise ValueError(f"cannot load ONNX model {self.path!r}: {e}") from None
        names = ({i.name for i in self.session.get_inputs()}, {o.name for o in self.session.get_outputs()})
        if names != self.IO:
            want = f"inputs {sorted(self.IO[0])} and outputs {sorted(self.IO[1])}"
            raise ValueError(f"{self.path!r} is not a {self.KIND} model: it has inputs {sorted(names[0])} and outputs "
                             f"{sorted(names[1])}, expected {want}")
        meta = self.session.get_modelmeta().custom_metadata_map
        self.meta = dict(meta)
        self.features = json.loads(meta.get("features", "[]"))
        self.domain = np.array(json.loads(meta.get("feature_domain", "[]")), dtype=np.float64).reshape(-1, 2)
        #: the detector kind the graph records (metadata ``kind``: ``boxes``, ``classifier``, ...); None for exports
        #: made before graphs recorded it
        self.kind: str | None = meta.get("kind")
        #: the model's bands (metadata ``bands``, centres and FWHM); None for exports made before graphs recorded
        #: them (``bands_nm``, centres alone, and ``fwhm_nm`` then)
        self.band_set: BandSet | None = None
        if "bands" in meta:
            try:
                self.band_set = BandSet.from_json(meta["bands"])
            except ValueError as e:
                raise ValueError(f"cannot load ONNX model {self.path!r}: its metadata 'bands' is not a band set: {e}") \
                    from None
        self.bands_nm = list(self.band_set.centers) if self.band_set is not None \
            else json.loads(meta.get("bands_nm", "[]"))
        self._pool: ThreadPoolExecutor | None = None

    def _config(self, config: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(config)
        if c.ndim == 1:
            c = c[None]
        if c.ndim != 2 or c.shape[1] != len(self.features):
            raise ValueError(f"config must be (N, {len(self.features)}) with features {self.features}, got {c.shape}")
        if np.issubdtype(c.dtype, np.integer):
            c = c.astype(np.float64)  # whole degrees are fine
        if not np.issubdtype(c.dtype, np.floating):
            raise ValueError(f"config must hold numbers (degrees, metres), got {c.dtype}")
        with np.errstate(over="ignore"):
            c = c.astype(np.float32)
        if not np.isfinite(c).all():
            raise ValueError("config holds NaN, infinite or out-of-float32-range values")
        ood = cast(np.ndarray, ((c < self.domain[:, 0]) | (c > self.domain[:, 1])).any(1)) if len(self.domain) \
            else np.zeros(len(c), bool)
        return c, ood


def model_inputs(path: str | os.PathLike) -> list[str]:
    """The input names of an ONNX model (``cube`` marks a detector, ``config`` alone a box model: ``OnboardBoxes``)."""
    import onnxruntime as ort

    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(f"cannot load ONNX model {str(path)!r}: {e}") from None
    return [i.name for i in sess.get_inputs()]


#: the detector kinds (metadata ``kind``) whose graph runs on the box head (``_split_box_graph``): the edge forms of
#: ``detectors.boxes.edge_detector_graph``; every other kind runs on the generic head, its graph as it is, per tile,
#: unless its metadata names its head (``onboard_head``). The built-in kinds' ``onboard_head``
#: (``detectors.registry.onboard_head``) agree with it: their graphs record no ``onboard_head`` (this module reads
#: graphs without torch, so without the registry)
BOX_HEAD_KINDS = frozenset({"boxes"})


def _edges_by_name(m: Any, inits: dict) -> tuple[list[str], np.ndarray, np.ndarray] | None:
    """The edge-matrix outputs and the edge constants (``det_edge_M``, ``det_edge_C``) of a box detector graph
    found by their node names: how exports made before graphs recorded their ``kind`` are recognised."""
    split = [n for n in m.graph.node if n.op_type == "Split" and list(n.input[:1]) == ["det_w"]]
    if len(split) != 1:
        return None
    return list(split[0].output), inits["det_edge_M"], inits["det_edge_C"]


def _edges_by_structure(m: Any, inits: dict) -> tuple[list[str], np.ndarray, np.ndarray] | None:
    """The same found by the graph's structure, whatever its names (a graph whose ``kind`` is a box kind): the one
    Split of Reshape(Add(MatMul(boxes, M), C)) (M, C initializers) whose every output feeds a MatMul."""
    producer = {o: n for n in m.graph.node for o in n.output}
    users: dict[str, list] = {}
    for n in m.graph.node:
        for i in n.input:
            users.setdefault(i, []).append(n)

    def made_by(name: str, op: str) -> Any:
        n = producer.get(name)
        return n if n is not None and n.op_type == op else None

    found = []
    for n in m.graph.node:
        if n.op_type != "Split" or not n.input:
            continue
        reshape = made_by(n.input[0], "Reshape")
        add = made_by(reshape.input[0], "Add") if reshape is not None else None
        if add is None:
            continue
        mm = next((made_by(i, "MatMul") for i in add.input if made_by(i, "MatMul") is not None), None)
        C = next((inits[i] for i in add.input if i in inits), None)
        M = next((inits[i] for i in mm.input if i in inits), None) if mm is not None else None
        if M is None or C is None or not all(any(u.op_type == "MatMul" for u in users.get(o, [])) for o in n.output):
            continue
        found.append((list(n.output), M, C))
    return found[0] if len(found) == 1 else None


def _split_box_graph(path: str, options: Any, by_name: bool = False) -> tuple | None:
    """A box detector graph (``detectors.boxes.edge_detector_graph``: edge matrices ``det_w0..`` from the
    configuration, then per pixel one MatMul per edge form, Min, Greater) as the per-frame part (an onnxruntime
    session: config -> edge matrices) and its per-pixel head rebuilt for tiles (``_EdgeHead``), so that tiles do not
    run the box network again. The edges are found by the graph's structure (``_edges_by_structure``; the caller
    knows from the metadata ``kind`` that it is a box graph) or, ``by_name``, by the node names of the box graph
    (``_edges_by_name``: exports without ``kind``). None when they are not found (a classifier), or without the
    ``onnx`` package: the whole graph then runs per tile (the same results)."""
    try:
        import onnx
        import onnxruntime as ort
        from onnx import numpy_helper
    except ImportError:
        return None
    try:
        m = onnx.load(path)
        inits = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
        found = (_edges_by_name if by_name else _edges_by_structure)(m, inits)
        if found is None:
            return None
        edges, M, C = found
        per_frame = ort.InferenceSession(_subgraph(m, ["config"], edges).SerializeToString(), options,
                                         providers=["CPUExecutionProvider"])
        return per_frame, _EdgeHead(m, M, C, len(edges), options)
    except Exception:  # noqa: BLE001 - any failure to split: run the whole graph per tile (same results)
        return None


def detector_head(meta: dict[str, str], path: str, options: Any) -> tuple[str, tuple | None]:
    """The head an ``OnboardDetector`` runs its graph on, chosen by the graph's metadata ``kind``: ``"boxes"`` (a
    kind of ``BOX_HEAD_KINDS``: the box head, ``_split_box_graph``'s per-frame session and tile head) or
    ``"generic"`` (any other kind: the graph as it is, per tile), and the box head's parts (None for the generic
    head). A graph without ``kind`` (exported before graphs recorded it) is told by today's node names instead
    (``_edges_by_name``: the Split of ``det_w``); a box graph whose edges are not found runs on the generic head
    (the same results, slower). A kind's graph may name its head in the metadata ``onboard_head`` (written by
    ``export.metadata`` where the kind asks for another head than ``BOX_HEAD_KINDS`` gives it), which wins."""
    kind = meta.get("kind")
    head = meta.get("onboard_head") or ("boxes" if kind is None or kind in BOX_HEAD_KINDS else "generic")
    if head != "boxes":
        return "generic", None
    split = _split_box_graph(path, options, by_name=kind is None)
    return ("generic", None) if split is None else ("boxes", split)


#: the float32 bit pattern of ``REFLECTANCE_MAX``: non-negative float32 values order as their bits (as unsigned
#: integers), while negative ones (the sign bit, -0.0 included) and NaN lie above it; one integer maximum of a tile
#: at or below this proves every value finite and within [0, REFLECTANCE_MAX]
_MAX_BITS = int(np.array(REFLECTANCE_MAX, dtype=np.float32).view(np.uint32))


#: the band (1080 nm: bright for skin, vegetation and most materials) whose value, when above the brightness floor,
#: proves a pixel's band sum above it (``OnboardDetector._apply_floor``)
FLOOR_BAND = 2


class _EdgeHead:
    """The per-pixel head of a box detector graph rebuilt for tiles: the edge forms, each one MatMul as in the
    graph, written into the rows of one (E, n) buffer, whose minimum over the rows (exact in any order) is the
    score and ``score > 0`` the mask, as the graph's Min and Greater. An edge form whose band weights are zero by
    construction (``det_edge_M`` and ``det_edge_C`` zero for those bands: L1, L2 use only g and r, L3, L4 only n
    and s) is a (1, 2) MatMul over those two bands' rows of the tile, which the tile buffer holds contiguously,
    instead of a (1, 4) one over all four: half the reads, and the products it skips are exact zeros. The inputs
    are views of one (4, n) tile buffer, the outputs rows of the edge buffer, all bound once per worker
    (``_TileBinding``). The same run gives the tile's minimum in ``FLOOR_BAND`` (``nir_min``): above the brightness
    floor, it settles the floor for the whole tile without another pass. ``sums`` is a second session, the band
    sum (g + r + n + s, in band order, as a MatMul with ones) for the floor where that does not settle it."""

    GROUPS = {"gr": (0, 2), "ns": (2, 4), "all": (0, 4)}

    def __init__(self, m: Any, M: np.ndarray, C: np.ndarray, e: int, options: Any):
        import onnxruntime as ort
        from onnx import TensorProto, helper, numpy_helper

        M, C = M.reshape(-1, e, 4), C.reshape(e, 4)  # the graph's edge constants (``det_edge_M``, ``det_edge_C``)
        used = (M != 0).any(0) | (C != 0)  # (edge, band): can this weight be non-zero for some box?
        self.e, self.groups = e, []
        for k in range(e):
            bands = set(np.flatnonzero(used[k]).tolist())
            self.groups.append(next(g for g, (lo, hi) in self.GROUPS.items() if bands <= set(range(lo, hi))))
        self.inputs = sorted(set(self.groups), key=list(self.GROUPS).index)
        F = TensorProto.FLOAT

        def session(nodes: list, inputs: list, outputs: list, inits: list) -> Any:
            graph = helper.make_graph(nodes, "torchskin_tile_head", inputs, outputs, inits)
            model = helper.make_model(graph, opset_imports=list(m.opset_import))
            model.ir_version = m.ir_version
            return ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])

        def rows(g: str) -> int:
            return self.GROUPS[g][1] - self.GROUPS[g][0]

        self.session = session(
            [helper.make_node("MatMul", [f"w{k}", g], [f"e{k}"]) for k, g in enumerate(self.groups)]
            + [helper.make_node("ReduceMin", ["nir"], ["nir_min"], keepdims=0)],
            [helper.make_tensor_value_info(g, F, [rows(g), "N"]) for g in self.inputs]
            + [helper.make_tensor_value_info(f"w{k}", F, [1, rows(g)]) for k, g in enumerate(self.groups)]
            + [helper.make_tensor_value_info("nir", F, [1, "N"])],
            [helper.make_tensor_value_info(f"e{k}", F, [1, "N"]) for k in range(e)]
            + [helper.make_tensor_value_info("nir_min", F, [])], [])
        self.sums = session([helper.make_node("MatMul", ["ones", "all"], ["bsum"])],
                            [helper.make_tensor_value_info("all", F, [4, "N"])],
                            [helper.make_tensor_value_info("bsum", F, [1, "N"])],
                            [numpy_helper.from_array(np.ones((1, 4), dtype=np.float32), "ones")])

    def bind(self, io: Any, sums: Any, tile: np.ndarray, edges: np.ndarray, total: np.ndarray,
             nir_min: np.ndarray) -> None:
        """Bind a (4, n) tile buffer's band groups and the rows of an (E, n) edge buffer to ``io``, and the tile
        and an (n,) band-sum buffer to ``sums`` (the head's and the band sum's bindings)."""
        n = tile.shape[1]
        for g in self.inputs:
            lo, hi = self.GROUPS[g]
            io.bind_cpu_input(g, tile[lo:hi])
        for k in range(self.e):
            io.bind_output(f"e{k}", "cpu", 0, np.float32, [1, n], edges[k].ctypes.data)
        io.bind_cpu_input("nir", tile[FLOOR_BAND:FLOOR_BAND + 1])
        io.bind_output("nir_min", "cpu", 0, np.float32, [], nir_min.ctypes.data)
        sums.bind_cpu_input("all", tile)
        sums.bind_output("bsum", "cpu", 0, np.float32, [1, n], total.ctypes.data)

    def frame_weights(self, edges: list[np.ndarray]) -> list[np.ndarray]:
        """One frame's edge matrices (``det_w0..``, each (1, 1, 4)) as the head's weights: per edge form the (1, 2)
        or (1, 4) float32 row of its band group."""
        ws = []
        for g, w in zip(self.groups, edges, strict=True):
            lo, hi = self.GROUPS[g]
            ws.append(np.ascontiguousarray(w.reshape(4)[lo:hi].reshape(1, hi - lo), dtype=np.float32))
        return ws

    def bind_weights(self, io: Any) -> list[np.ndarray]:
        """Weight buffers bound to ``io`` once, which each frame's ``frame_weights`` are copied into (the binding
        reads them in place); returns them (to be kept referenced while bound)."""
        ws = []
        for k, g in enumerate(self.groups):
            lo, hi = self.GROUPS[g]
            ws.append(np.zeros((1, hi - lo), dtype=np.float32))
            io.bind_cpu_input(f"w{k}", ws[-1])
        return ws


class _TileBinding:
    """One worker's buffers for tiles of ``n`` pixels and the onnxruntime bindings over them, made once and kept
    by the detector between calls (binding costs ~0.1 ms a worker and a call otherwise): the (4, n) tile, the
    (E, n) edge rows and (n,) band sum of a split box graph (``_EdgeHead``), its weight buffers, the floor's (n,)
    bool scratch; ``frame``: the frame whose weights (or configuration) are bound, -1 at the start of a call."""

    def __init__(self, det: OnboardDetector, n: int):
        self.head = det._split[1] if det._split is not None else None
        rows = self.head.e if self.head is not None else 0
        self.t, self.edges = np.empty((4, n), dtype=np.float32), np.empty((rows, n), dtype=np.float32)
        self.total, self.dark = np.empty(n, dtype=np.float32), np.empty(n, dtype=bool)
        self.bits = self.t.view(np.uint32)  # the tile's values as unsigned integers (``_MAX_BITS``)
        self.nir_min = np.zeros((), dtype=np.float32)  # the head's minimum of the tile's FLOOR_BAND
        self.frame, self.ws = -1, []
        if self.head is not None:
            self.io, self.sums = self.head.session.io_binding(), self.head.sums.io_binding()
            self.head.bind(self.io, self.sums, self.t, self.edges, self.total, self.nir_min)
            self.ws = self.head.bind_weights(self.io)
        else:  # a plain (4, n) array, bound as (1, 4, 1, n): numpy fills it faster than a 4-d view
            self.io, self.sums = det.session.io_binding(), None
            self.io.bind_cpu_input("cube", self.t.reshape(1, 4, 1, n))

    def band_sum(self) -> None:
        """The band sum of the tile into ``total`` (the head's ``sums`` session)."""
        self.head.sums.run_with_iobinding(self.sums)  # type: ignore[union-attr]


def _subgraph(m: Any, inputs: list[str], outputs: list[str]) -> Any:
    """The part of ONNX model ``m`` that computes ``outputs`` from ``inputs`` (and initializers): the nodes found
    walking back from the outputs, stopping at the inputs."""
    from onnx import TensorProto, helper

    producer = {o: n for n in m.graph.node for o in n.output}
    inits = {t.name: t for t in m.graph.initializer}
    types = {v.name: v for v in [*m.graph.input, *m.graph.output]}
    seen: set[int] = set()
    todo = list(outputs)
    while todo:
        name = todo.pop()
        if name in inputs or name in inits or name == "":
            continue
        node = producer[name]  # KeyError: the outputs need something besides the inputs
        if id(node) not in seen:
            seen.add(id(node))
            todo += list(node.input)
    order = [n for n in m.graph.node if id(n) in seen]  # the original order is topological
    used = {i for n in order for i in n.input}

    def info(name: str) -> Any:
        return types.get(name) or helper.make_tensor_value_info(name, TensorProto.FLOAT, None)

    graph = helper.make_graph(order, "part", [info(i) for i in inputs], [info(o) for o in outputs],
                              [inits[k] for k in sorted(used & set(inits))])
    part = helper.make_model(graph, opset_imports=list(m.opset_import))
    part.ir_version = m.ir_version
    return part


class OnboardBoxes(_Model):
    """The boxes of a ``boxes``-kind model, exported as ``boundaries.onnx`` (or ``baseline_box.onnx``) and run by
    onnxruntime: configuration (N, k) -> boxes (N, 5) (b1, b2, c1, c2, d1; see ``box_order`` in the metadata; models
    exported before the NDVN rule give (N, 4))."""

    KIND = "boundaries (configuration -> boxes)"
    IO = ({"config"}, {"boxes"})

    def __call__(self, config: ArrayLike) -> dict:
        """``{"boxes": (N, 5) float32, "out_of_domain": (N,) bool}`` of configurations (N, k) or (k,)."""
        c, ood = self._config(config)
        (boxes,) = self.session.run(None, {"config": c})
        return {"boxes": boxes, "out_of_domain": ood}


class OnboardDetector(_Model):
    """``detector.onnx`` run by onnxruntime: reflectance cube (B, 4, H, W) + configuration (B, k) -> mask and
    score (the torch reference: ``torchskin.detectors.boxes.BoxDetector`` or
    ``torchskin.detectors.classifier.ClassifierDetector``).

    Large frames are cut into tiles of ``tile`` pixels (each band's run of the flattened frame) that
    ``threads`` workers (the calling thread and a pool; one onnxruntime session, one intra-op thread each)
    pull from a shared queue, outputs bound straight into the result arrays, so the intermediates stay in
    cache: the frame is read from memory about once. An OnboardDetector keeps its tile buffers and pool between
    calls: create it once, and use one per calling thread (calls on one object must not overlap).

    The head the tiles run on (``head_name``) follows the graph's metadata ``kind`` (``detector_head``): a box
    kind's graph computes its edge matrices once per frame and runs a rebuilt per-pixel head ("boxes"); any other
    kind's graph runs as it is ("generic"). Graphs exported before they recorded ``kind`` are told by their node
    names. The model's bands come from the metadata ``bands`` (``band_set``, centres and FWHM), else ``bands_nm``."""

    KIND = "detector (cube + configuration -> mask, score)"
    IO = ({"cube", "config"}, {"mask", "score"})

    def __init__(self, path: str | os.PathLike = SHIPPED_DETECTOR, threads: int | None = None, tile: int = 65536):
        super().__init__(path, threads)
        if tile < 1024:
            raise ValueError(f"tile must be >= 1024 pixels, got {tile}")
        self.tile = int(tile)
        self._bindings: dict[int, dict[int, _TileBinding]] = {}  # per worker, per tile size (``_TileBinding``)
        #: the head the graph runs on, by its metadata ``kind`` (``detector_head``): "boxes" or "generic"
        self.head_name, self._split = detector_head(self.meta, self.path, self.session.get_session_options())

    @staticmethod
    def _check_tile(t: np.ndarray, b: int, clipped: np.ndarray | None) -> tuple[float, float, int]:
        """Validate a (4, n) tile while it is in cache: its smallest and largest value and how many exceed
        ``REFLECTANCE_MAX`` (NaN propagates), clipping negative values to 0 (counted in ``clipped[b]``) when
        ``clipped`` is given. Only for a tile that failed the one-pass test of ``_run_tiles`` (its values' integer
        maximum at most ``_MAX_BITS``: every value within [0, ``REFLECTANCE_MAX``], the usual calibrated tile); the
        largest value goes to ``check_reflectance_range`` (``REFLECTANCE_CEILING``) with the frame's."""
        low, top = t.min(), t.max()
        over = int(np.count_nonzero(t > REFLECTANCE_MAX)) if top > REFLECTANCE_MAX else 0
        if clipped is not None:
            clipped[b] += np.count_nonzero(t < 0)
            np.maximum(t, 0, out=t)  # NaN stays NaN
        return low, top, over

    @staticmethod
    def _apply_floor(t: np.ndarray, m: np.ndarray, floor: float, total: np.ndarray,
                     band_sum: Callable[[], None] | None = None, dark: np.ndarray | None = None) -> None:
        """``m &= t.sum(0) > floor`` (the band sum in band order, as float32) for a non-negative (4, n) tile ``t``
        and its mask ``m`` (``__call__`` refuses or clips negative values before the floor). A masked pixel whose
        third band (1080 nm: bright for skin, vegetation and most materials) lies above the floor keeps its mask
        without a sum: its sum is at least that band (the others are non-negative, and float32 addition of
        non-negative terms never rounds below either), so only the masked pixels dark in that band (``dark``, an
        (n,) bool scratch buffer) are summed: nothing more where there are none (most tiles: one comparison over
        a quarter of the tile), at those pixels alone when they are few (the same sums), and over the tile into
        ``total`` otherwise (by ``band_sum()`` when given: the head's ``sums`` session)."""
        if not m.any():  # a tile without skin (most of a frame's)
            return
        dark = np.empty(len(m), dtype=bool) if dark is None else dark
        np.less_equal(t[FLOOR_BAND], floor, out=dark)
        np.logical_and(dark, m, out=dark)
        count = np.count_nonzero(dark)
        if not count:
            return
        if 16 * count < len(m):
            idx = np.flatnonzero(dark)
            s = t[0, idx]
            for k in range(1, t.shape[0]):
                s += t[k, idx]
            m[idx[~(s > floor)]] = False
            return
        if band_sum is not None:
            band_sum()
        else:
            np.add(t[0], t[1], out=total)
            for k in range(2, t.shape[0]):
                np.add(total, t[k], out=total)
        np.logical_and(m, total > floor, out=m)

    def _run_tiles(self, flat: np.ndarray, c: np.ndarray, mask: np.ndarray, score: np.ndarray,
                   take: Callable[[], tuple[int, int, int] | None], slot: int = 0, clipped: np.ndarray | None = None,
                   floor: float = 0.0, frame_weights: Callable[[int], list[np.ndarray]] | None = None,
                   ) -> tuple[float, float, int]:
        """Run the jobs (frame, first, last pixel) that ``take()`` hands out (None: done) with tile buffers
        ``slot``; return the smallest and largest reflectance seen before clipping (NaN if any) and how many values
        exceed ``REFLECTANCE_MAX`` (``_check_tile``; (0, 0, 0) when all lie within [0, ``REFLECTANCE_MAX``]).
        ``clipped`` (per-frame counts): set negative values to 0 and count them. ``floor``: pixels whose band sum
        is not above it are not skin.
        A box graph runs split (``_split_box_graph``): its edge matrices once per frame, its per-pixel head
        (``_EdgeHead``) per tile; other graphs run whole per tile."""
        from onnxruntime import OrtValue

        head = self._split[1] if self._split is not None else None
        low, high, over = 0.0, 0.0, 0
        run = head.session.run_with_iobinding if head is not None else self.session.run_with_iobinding
        minimum, greater = np.minimum.reduce, np.greater
        bindings = self._bindings.setdefault(slot, {})  # this worker's alone
        for tb in bindings.values():
            tb.frame = -1  # nothing of this call bound yet
        for b, lo, hi in iter(take, None):
            n = hi - lo
            tb = bindings.get(n) or self._binding(bindings, n)
            t, edges = tb.t, tb.edges
            t[...] = flat[b, :, lo:hi]
            # the usual tile's one pass: every value within range (``_MAX_BITS``), else the full check
            checked = None if int(tb.bits.max()) <= _MAX_BITS else self._check_tile(t, b, clipped)
            if checked is not None:
                low, high, over = np.minimum(low, checked[0]), np.maximum(high, checked[1]), over + checked[2]
            if b != tb.frame:  # a frame's edge matrices from its configuration alone (batch 1, as the whole graph)
                if head is not None:  # copied into the bound weight buffers
                    for w, v in zip(tb.ws, frame_weights(b), strict=True):  # type: ignore[misc]
                        w[...] = v
                else:
                    tb.io.bind_cpu_input("config", c[b:b + 1])
                tb.frame = b
            m, sc = mask[b, lo:hi], score[b, lo:hi]
            if head is not None:
                run(tb.io)
                minimum(edges, axis=0, out=sc)  # the graph's Min
                greater(sc, 0, out=m)  # and its Greater
            else:  # outputs written in place (an OrtValue over the result arrays binds faster than bind_output)
                tb.io.bind_ortvalue_output("mask", OrtValue.ortvalue_from_numpy(m.reshape(1, 1, n)))
                tb.io.bind_ortvalue_output("score", OrtValue.ortvalue_from_numpy(sc.reshape(1, 1, n)))
                run(tb.io)
            if checked is not None and not np.isfinite(sc.min()):  # +inf in a band gives a -inf (or NaN) score
                low = np.nan
            if floor > 0 and not (head is not None and tb.nir_min > floor):  # (one band above the floor: so is
                self._apply_floor(t, m, floor, tb.total, tb.band_sum if head is not None else None, tb.dark)  # the sum)
        return low, high, over

    def _binding(self, bindings: dict[int, _TileBinding], n: int) -> _TileBinding:
        """A worker's buffers and bindings for tiles of ``n`` pixels, made on first use and kept in its
        ``bindings``: the full tile's and one ragged size's (a frame's last tile; another size replaces it)."""
        if n != self.tile:
            for k in [k for k in bindings if k != self.tile]:
                del bindings[k]
        tb = bindings[n] = _TileBinding(self, n)
        return tb

    def pixels(self, reflectance: ArrayLike, config: ArrayLike, chunk: int = 65536) -> dict:
        """The detector graph on separate pixels, each with its own configuration: ``reflectance`` (n, 4) and
        ``config`` (n, k) run as a (n, 4, 1, 1) cube in chunks of ``chunk`` pixels (negative values clipped to 0,
        as ``negative="clip"``; no brightness floor). Returns ``mask`` (n,) bool and ``score`` (n,) float32."""
        r = np.asarray(reflectance, dtype=np.float32)
        if r.ndim != 2 or r.shape[1] != 4:
            raise ValueError(f"reflectance must be (n, 4), got shape {r.shape}")
        if not np.isfinite(r).all():
            raise ValueError("reflectance holds NaN or infinite values")
        c, _ = self._config(config)
        if c.shape[0] != r.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for {r.shape[0]} pixels")
        mask, score = np.empty(len(r), dtype=bool), np.empty(len(r), dtype=np.float32)
        for lo in range(0, len(r), chunk):
            hi = min(lo + chunk, len(r))
            cube = np.maximum(r[lo:hi], 0).reshape(hi - lo, 4, 1, 1)
            m, sc = self.session.run(None, {"cube": cube, "config": c[lo:hi]})
            mask[lo:hi], score[lo:hi] = m.reshape(-1), sc.reshape(-1)
        return {"mask": mask, "score": score}

    @staticmethod
    def _check_low(low: float, high: float = 0.0, clip: bool = False, above: float | None = 1.0) -> None:
        """``ValueError`` for a cube whose smallest and largest values (before clipping) are ``low`` and
        ``high``, with a share ``above`` of its values above ``REFLECTANCE_MAX``: NaN, out of meaning
        (``check_reflectance_range``), or negative unless ``clip``. ``above`` None: the upper bounds (the share
        and ``REFLECTANCE_CEILING``) are the caller's (``range_check=False``)."""
        if not (np.isfinite(low) and np.isfinite(high)):
            raise ValueError("cube holds NaN or infinite reflectance")
        check_reflectance_range(low, 0.0 if above is None else high, 0.0 if above is None else above)
        if low < 0 and not clip:
            raise ValueError(f"cube holds negative reflectance (min {float(low):.3g}); noise on dark pixels? "
                             "negative='clip' (torchskin detect --clip-negative) sets it to 0")

    def _check_cube(self, cube: ArrayLike) -> np.ndarray:
        """``cube`` as an array, after the checks of rank, band count, dtype and size (``ValueError``)."""
        x = np.asarray(cube)
        if x.ndim != 4:
            raise ValueError(f"cube must have rank 4 (B, bands, H, W), got shape {x.shape}")
        if x.shape[1] != len(self.bands_nm or [0] * 4):
            raise ValueError(f"cube must have {len(self.bands_nm)} bands ({self.bands_nm} nm) on axis 1, "
                             f"got {x.shape[1]}")
        if x.size == 0:
            raise ValueError(f"cube is empty: shape {x.shape}")
        try:
            return as_float32(x)  # float64, float16, either byte order, integers: converted alike
        except ValueError as e:
            raise ValueError(f"cube {e}") from None

    @staticmethod
    def _check_out(out: tuple[np.ndarray, np.ndarray], shape: tuple[int, int, int]) -> None:
        """``ValueError`` unless ``out`` is a (mask, score) pair of writeable C-contiguous bool and float32 arrays
        of ``shape``."""
        if (not isinstance(out, (tuple, list)) or len(out) != 2
                or not all(isinstance(a, np.ndarray) for a in out)):
            raise ValueError("out must be a (mask, score) pair of numpy arrays")
        for a, dt, name in ((out[0], np.bool_, "mask"), (out[1], np.float32, "score")):
            if a.shape != shape or a.dtype != dt or not a.flags.c_contiguous or not a.flags.writeable:
                raise ValueError(f"out {name} must be a writeable C-contiguous {np.dtype(dt).name} array of shape "
                                 f"{shape}, got {a.dtype} {a.shape}")

    @property
    def default_min_reflectance(self) -> float:
        """The brightness floor the model was evaluated with (metadata ``min_reflectance``; 0 when absent)."""
        try:
            return float(self.meta.get("min_reflectance", 0.0))
        except ValueError:
            return 0.0

    def __call__(self, cube: np.ndarray, config: ArrayLike, out: tuple[np.ndarray, np.ndarray] | None = None,
                 negative: str = "error", min_reflectance: float | None = None, range_check: bool = True) -> dict:
        """Detect skin in ELM reflectance frames.

        Args:
            cube: reflectance (float32; other float and integer dtypes are converted), bands (544, 633, 1080,
                1580 nm: the model's ``bands_nm``) on axis 1; finite, within [``REFLECTANCE_MIN``,
                ``REFLECTANCE_MAX``] (up to ``REFLECTANCE_CEILING`` in at most ``REFLECTANCE_MAX_SHARE`` of its
                values), and non-negative unless ``negative="clip"``.
            config: each frame's configuration features in the model's order and units (``features``).
            out: optional preallocated (mask, score) arrays, bool and float32, C-contiguous, that receive the
                result (an onboard loop reuses them; their content is undefined if the call raises).
            negative: "error" (default) raises on negative reflectance; "clip" sets it to 0 (the caller's cube
                is not modified) and reports the count per frame as ``clipped_values``.
            min_reflectance: > 0: pixels whose mean reflectance over the bands is not above it are never skin
                (at the noise floor the indices are ratios of noise; e.g. 0.005 for ~3e-4 noise); 0 keeps the
                rules alone; None (default): the floor the model was evaluated with (``default_min_reflectance``,
                from its metadata).
            range_check: False leaves the share of values above ``REFLECTANCE_MAX`` and the bound
                ``REFLECTANCE_CEILING`` to the caller, who checks them over a whole frame cut into calls
                (``detect_file``'s row tiles, so that a cube in per cent gets its hint); the smallest value, NaN and
                negative values are still refused per call.

        Shape:
            cube: (B, 4, H, W); config: (B, k) (or (k,) for B = 1); out, mask, score: (B, H, W);
            out_of_domain, clipped_values: (B,).

        Returns:
            ``{"mask": bool, "score": float32 (positive inside), "out_of_domain": bool per frame}`` and, with
            ``negative="clip"``, ``"clipped_values"`` (int64 per frame). ``ValueError`` on invalid input.
        """
        if negative not in ("error", "clip"):
            raise ValueError(f"negative must be 'error' or 'clip', got {negative!r}")
        if min_reflectance is None:
            min_reflectance = self.default_min_reflectance
        if not (0.0 <= float(min_reflectance) < 1.0):
            raise ValueError(f"min_reflectance must lie in [0, 1), got {min_reflectance}")
        x = self._check_cube(cube)
        c, ood = self._config(config)
        if c.shape[0] != x.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for a batch of {x.shape[0]} frames")
        B, _, H, W = x.shape
        n = H * W
        if out is not None:
            self._check_out(out, (B, H, W))
        clipped = np.zeros(B, dtype=np.int64) if negative == "clip" else None
        extra = {} if clipped is None else {"clipped_values": clipped}
        floor = x.shape[1] * float(min_reflectance)  # on the band sum
        if B * n <= self.tile:  # small frames: one call
            top = x.max()
            share = np.count_nonzero(x > REFLECTANCE_MAX) / x.size if top > REFLECTANCE_MAX else 0.0
            self._check_low(x.min(), top, clipped is not None, share if range_check else None)
            if clipped is not None:
                clipped += np.count_nonzero(x < 0, axis=(1, 2, 3))
                x = np.maximum(x, 0)
            mask, score = self.session.run(None, {"cube": np.ascontiguousarray(x), "config": c})
            if not np.isfinite(score.min()):
                self._check_low(np.nan)
            if floor > 0:
                mask &= x.sum(1) > floor
            if out is not None:
                out[0][...], out[1][...] = mask, score
                mask, score = out
            return {"mask": mask.astype(bool, copy=False), "score": score, "out_of_domain": ood, **extra}
        flat = x.reshape(B, 4, n)
        if out is not None:
            mask, score = out[0].reshape(B, n), out[1].reshape(B, n)
        else:
            mask, score = np.empty((B, n), dtype=bool), np.empty((B, n), dtype=np.float32)
        jobs = [(b, s, min(s + self.tile, n)) for b in range(B) for s in range(0, n, self.tile)]
        k = min(self.threads, len(jobs))
        counts = [np.zeros(B, dtype=np.int64) if clipped is not None else None for _ in range(k)]  # per worker
        queue, lock = iter(jobs), threading.Lock()

        def take() -> tuple[int, int, int] | None:  # workers pull the next tile: a worker that starts late simply takes fewer
            with lock:
                return next(queue, None)

        weights: dict[int, list[np.ndarray]] = {}  # per frame: its edge matrices as the head's weights

        def frame_weights(b: int) -> list[np.ndarray]:  # from the frame's configuration alone (batch 1, as the
            if b not in weights:  # whole graph), once per frame (two workers on a new frame: the same values)
                per_frame, head = cast(tuple, self._split)
                weights[b] = head.frame_weights(per_frame.run(None, {"config": c[b:b + 1]}))
            return weights[b]

        if self._split is not None:
            frame_weights(0)  # before the workers start, which all begin on frame 0
        if k > 1 and self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="torchskin-detect")
        futures = [cast("ThreadPoolExecutor", self._pool).submit(self._run_tiles, flat, c, mask, score, take, i,
                                                                 counts[i], floor, frame_weights)
                   for i in range(1, k)]
        ranges = []
        try:  # the calling thread is worker 0
            ranges.append(self._run_tiles(flat, c, mask, score, take, 0, counts[0], floor, frame_weights))
        finally:  # never return (or raise) while a worker still writes into the outputs
            ranges += [f.result() for f in futures]
        lows, highs, overs = zip(*ranges)
        # NaN propagates; the outputs are discarded: no mask comes back from an invalid cube
        self._check_low(np.min(lows), np.max(highs), clipped is not None,
                        sum(overs) / x.size if range_check else None)
        if clipped is not None:
            clipped += np.sum(cast(list[np.ndarray], counts), axis=0)
        if out is not None:
            return {"mask": out[0], "score": out[1], "out_of_domain": ood, **extra}
        return {"mask": mask.reshape(B, H, W), "score": score.reshape(B, H, W), "out_of_domain": ood, **extra}



# ------------------------------------------------------------------------- ELM for camera frames (numpy only)
def panel_signal(frame: ArrayLike, roi: Sequence[int], erode: int = 1) -> np.ndarray:
    """Per-band median of ``frame`` (bands, H, W) over the region ``roi`` = (y0, y1, x0, x1) shrunk by ``erode``
    pixels on every side (the panel's edges mix with the background)."""
    f = np.asarray(frame)
    if f.ndim != 3:
        raise ValueError(f"frame must be (bands, H, W), got shape {f.shape}")
    if int(erode) < 0:
        raise ValueError(f"erode must be >= 0 pixels, got {erode}")
    y0, y1, x0, x1 = (int(v) for v in roi)
    H, W = f.shape[1:]
    if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
        raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} must satisfy 0 <= Y0 < Y1 <= {H} and 0 <= X0 < X1 <= {W}")
    e = int(erode)
    if y1 - y0 <= 2 * e or x1 - x0 <= 2 * e:
        raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} has no interior pixel after eroding {e} px per side")
    v = f[:, y0 + e:y1 - e, x0 + e:x1 - e].reshape(f.shape[0], -1).astype(np.float64)
    if not np.isfinite(v).all():
        raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} holds NaN or infinite values")
    return np.median(v, axis=1)


def check_panel_regions(rois: Sequence[Sequence[int]]) -> None:
    """``ValueError`` when two panel regions (y0, y1, x0, x1) are the same or overlap: two panels cannot share a
    pixel, so one of them is mistyped, and the line through them would be fitted to one panel's signal twice.

    >>> check_panel_regions([(0, 4, 0, 4), (0, 4, 4, 8)])  # side by side: fine
    >>> check_panel_regions([(0, 4, 0, 4), (2, 6, 2, 6)])
    Traceback (most recent call last):
    ...
    ValueError: panel regions 0:4:0:4 and 2:6:2:6 overlap (4 pixels): each panel needs its own region
    """
    boxes = [tuple(int(v) for v in r) for r in rois]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            (a0, a1, b0, b1), (c0, c1, d0, d1) = boxes[i], boxes[j]
            n = max(0, min(a1, c1) - max(a0, c0)) * max(0, min(b1, d1) - max(b0, d0))
            if n:
                what = "are the same region" if boxes[i] == boxes[j] else f"overlap ({n} pixels)"
                raise ValueError(f"panel regions {':'.join(map(str, boxes[i]))} and {':'.join(map(str, boxes[j]))} "
                                 f"{what}: each panel needs its own region")


def elm_fit(frame: ArrayLike, panels: Sequence[tuple[Sequence[int], ArrayLike]], erode: int = 1) -> dict:
    """Empirical line L = gain·ρ + offset per band (eqs 2.5.5-2.5.6) from reference panels in ``frame``
    (bands, H, W): ``panels`` is a sequence of (roi, reflectance), the reflectance a scalar or one value per
    band in (0, 1]; the panels' regions must not overlap (``check_panel_regions``). Two panels give the exact
    line through them; more give the least-squares line. ``residual``: per band, the RMS over the panels of the
    fitted minus the known reflectance ((L - offset) / gain - ρ; 0 for two panels)."""
    f = np.asarray(frame)
    if f.ndim != 3:
        raise ValueError(f"frame must be (bands, H, W), got shape {f.shape}")
    if len(panels) < 2:
        raise ValueError(f"ELM needs at least 2 reference panels, got {len(panels)}")
    nb = f.shape[0]
    check_panel_regions([roi for roi, _ in panels])
    refs, sig = [], []
    for roi, rho in panels:
        refs.append(panel_reference(rho, nb))
        sig.append(panel_signal(f, roi, erode))
    return elm_line(np.stack(refs), np.stack(sig))


def panel_reference(rho: ArrayLike, nb: int) -> np.ndarray:
    """A panel's reflectance per band (``nb``) from one value or one per band, each in (0, 1]."""
    r = np.broadcast_to(np.asarray(rho, dtype=np.float64), (nb,)) if np.ndim(rho) == 0 else np.asarray(rho, np.float64)
    if r.shape != (nb,):
        raise ValueError(f"panel reflectance must be one value or {nb} (one per band), got {np.shape(rho)}")
    if not (np.all(r > 0) and np.all(r <= 1)):
        raise ValueError(f"panel reflectance must lie in (0, 1], got {r.tolist()}")
    return r


def elm_line(R: np.ndarray, L: np.ndarray) -> dict:
    """The empirical line per band through panels of known reflectance ``R`` and measured signal ``L``, both
    (panels, bands): ``elm_fit``'s result (``calibrate_file`` measures the signals from row tiles)."""
    dR = R - R.mean(0)
    var = (dR ** 2).sum(0)
    if np.any(var < 1e-12):
        bad = np.flatnonzero(var < 1e-12).tolist()
        raise ValueError(f"panel reflectances must differ in every band (band(s) {bad} have equal references)")
    gain = (dR * (L - L.mean(0))).sum(0) / var
    if np.any(gain <= 0):
        bad = np.flatnonzero(gain <= 0).tolist()
        raise ValueError(f"panel signals do not grow with reflectance in band(s) {bad}: regions or reflectances "
                         "swapped, or a panel saturated or in shadow?")
    offset = L.mean(0) - gain * R.mean(0)
    resid = np.sqrt((((L - offset) / gain - R) ** 2).mean(0))
    return {"gain": gain, "offset": offset, "signals": L, "references": R, "residual": resid}


def elm_apply(cube: ArrayLike, gain: ArrayLike, offset: ArrayLike) -> np.ndarray:
    """Reflectance (float32) of signals ``cube`` (bands, H, W) or (B, bands, H, W): (L - offset) / gain."""
    x = np.asarray(cube)
    g, o = np.asarray(gain, np.float64), np.asarray(offset, np.float64)
    if x.ndim not in (3, 4) or g.shape != (x.shape[-3],) or o.shape != g.shape:
        raise ValueError(f"cube must be (bands, H, W) or (B, bands, H, W) with one gain and offset per band; got "
                         f"cube {x.shape}, gain {g.shape}, offset {o.shape}")
    if not np.all(np.isfinite(g)) or np.any(g <= 0) or not np.all(np.isfinite(o)):
        raise ValueError("gain must be finite and > 0 and offset finite in every band")
    inv = (1.0 / g)[:, None, None]
    return ((x - o[:, None, None]) * inv).astype(np.float32)


# ------------------------------------------------------------------------------------------------ reading cubes
#: ``load_cube`` checks a cube for NaN and infinities this many values at a time (bounded temporaries)
_FINITE_CHUNK = 1 << 22


def load_cube(path: StrPath, option: str = "--cube", max_megapixels: float = MAX_MEGAPIXELS) -> np.ndarray:
    """The cube a command reads (``detect``, ``calibrate``): a ``.npy`` file (no pickles, no ``.npz``) of real
    numbers, (bands, H, W) or (frames, bands, H, W), non-empty and finite, returned as native float32
    (``io.as_float32``: float64, float16, big-endian and integer files convert alike). Its frame size (H x W)
    must be at most ``max_megapixels`` (``io.MAX_MEGAPIXELS``, what ``--max-megapixels`` raises), checked from the
    header before any data is read; a native float32 file is memory-mapped rather than read whole. Every
    problem is a one-line ``ValueError`` naming ``option`` and the file: the header's checks are
    ``cubefiles.open_npy``'s (the one ``.npy`` reader: a file shorter than its header's cube is refused as
    truncated), then the values' (finite)."""
    from .cubefiles import open_npy
    from .errors import check_input_file

    p = check_input_file(path, option, (".npy",))
    if not (np.isfinite(max_megapixels) and max_megapixels > 0):
        raise ValueError(f"--max-megapixels must be a positive number, got {max_megapixels}")
    x = as_float32(open_npy(p, option, one_frame=False, max_megapixels=max_megapixels))
    flat = x.reshape(-1)
    for lo in range(0, flat.size, _FINITE_CHUNK):  # chunks: no temporary the size of the cube
        if not np.isfinite(flat[lo:lo + _FINITE_CHUNK]).all():
            raise ValueError(f"{option} {str(p)!r} holds NaN or infinite values")
    return x


# ------------------------------------------------------------------------------ the model's bands from any cube
#: the widest step (nm) between a cube's samples inside (or bracketing) a model band's response that
#: ``band_plan`` interpolates across: a wider gap (a cube with a missing detector range) is refused
MAX_SAMPLE_GAP_NM = 50.0


def band_plan(cube_bands: Sequence[float], cube_fwhm: Sequence[float] | None, model_bands: Sequence[float],
              model_fwhm: Sequence[float] | None = None) -> dict:
    """How to read the model's bands from a cube with bands ``cube_bands`` (nm): ``{"kind": "reorder", "order":
    [...]}`` when the cube has exactly the model's bands (``match_bands``: used as they are, reordered), else
    ``{"kind": "synthesis", "matrix": (n_model, n_cube) float64}``, each row summing to 1: the model's band
    (``model_fwhm``, 0 = monochromatic: the renderer's default bands) by the band response model of the renderer
    (``bands.response_weights``) on the cube's spectrum, linearly interpolated between its samples onto a 1 nm grid
    over the band's support. The cube's own FWHM (``cube_fwhm``) is not deconvolved: its samples are taken as the
    spectrum at their centres. ``ValueError`` naming the band and the cube's range when the cube does not cover
    a band, or leaves a gap over ``MAX_SAMPLE_GAP_NM`` inside it.

    >>> band_plan([1580, 544, 1080, 633], None, [544, 633, 1080, 1580])
    {'kind': 'reorder', 'order': [1, 3, 2, 0]}
    >>> p = band_plan(range(450, 1651, 10), None, [544, 633, 1080, 1580])
    >>> p["kind"], p["matrix"].shape, [round(float(w), 2) for w in p["matrix"][0, 9:11]]
    ('synthesis', (4, 121), [0.6, 0.4])
    """
    from .bands import SUPPORT_FWHM, response_weights

    cb = np.asarray([float(b) for b in cube_bands], dtype=np.float64)
    mf = [0.0] * len(model_bands) if model_fwhm is None else [float(f) for f in model_fwhm]
    if len(cb) == len(model_bands):
        try:
            return {"kind": "reorder", "order": match_bands(cb.tolist(), model_bands)}
        except ValueError:
            pass
    order = np.argsort(cb)
    x = cb[order]
    lo, hi = float(x[0]), float(x[-1])
    rows = []
    for c, f in zip((float(b) for b in model_bands), mf):
        s_lo, s_hi = c - SUPPORT_FWHM * f, c + SUPPORT_FWHM * f
        near = np.abs(x - c)
        if f == 0 and near.min() <= BAND_MATCH_NM and not (lo <= c <= hi):
            s_lo = s_hi = float(x[near.argmin()])  # a band just past the cube's last sample, within the match
        if len(x) < 2 or s_lo < lo - 1e-9 or s_hi > hi + 1e-9:
            raise ValueError(f"the cube's {len(x)} bands span {lo:g}..{hi:g} nm, which does not cover the model's "
                             f"{c:g} nm band (its response needs {s_lo:g}..{s_hi:g} nm)")
        a = max(int(np.searchsorted(x, s_lo, side="right")) - 1, 0)
        b = min(int(np.searchsorted(x, s_hi, side="left")), len(x) - 1)
        gap = float(np.diff(x[a:b + 1]).max()) if b > a else 0.0
        if gap > MAX_SAMPLE_GAP_NM:
            raise ValueError(f"the cube's bands ({lo:g}..{hi:g} nm) leave a {gap:g} nm gap inside the model's {c:g} nm "
                             f"band (at most {MAX_SAMPLE_GAP_NM:g} nm between samples is interpolated)")
        grid = np.array([s_lo]) if f == 0 else np.linspace(s_lo, s_hi, max(math.ceil(s_hi - s_lo), 8) + 1)
        interp = np.stack([response_weights(x, g, 0.0) for g in np.clip(grid, lo, hi)])  # cube samples -> grid
        w = response_weights(grid, s_lo if f == 0 else c, f) @ interp
        row = np.zeros(len(x))
        row[order] = w
        rows.append(row)
    return {"kind": "synthesis", "matrix": np.stack(rows)}


def apply_plan(plan: dict, block: np.ndarray) -> np.ndarray:
    """The model's bands (n_model, rows, W) float32 from a cube's rows ``block`` (n_cube, rows, W) by ``plan``
    (a synthesis summed in float64 per pixel, then rounded)."""
    if plan["kind"] == "reorder":
        order = plan["order"]
        return block if order == list(range(block.shape[0])) else np.ascontiguousarray(block[order])
    m = plan["matrix"]
    out = np.zeros((m.shape[0], *block.shape[1:]), dtype=np.float64)
    for j in range(m.shape[0]):  # per element, over the band's few non-zero weights: a pixel's value depends on
        for k in np.flatnonzero(m[j]):  # its spectrum alone, not on the tile's size or its place in it (a GEMM's
            out[j] += m[j, k] * block[k].astype(np.float64)  # blocking would change the rounding with the tile)
    return out.astype(np.float32)


def model_fwhm(det: _Model) -> list[float] | None:
    """The model's band FWHM (nm) from its metadata ``bands`` (or, in exports without it, ``fwhm_nm``); None
    (monochromatic, the renderer's default bands) when it has none."""
    if det.band_set is not None:
        return [b.fwhm_nm for b in det.band_set]
    try:
        f = json.loads(det.meta.get("fwhm_nm", "null"))
        return None if f is None else [float(v) for v in f]
    except (ValueError, TypeError):
        return None


# ---------------------------------------------------------------------------------------- streaming a file
#: bytes of the input cube's rows per tile of ``detect_file`` and ``calibrate_file`` when ``tile_rows`` is None:
#: the rows per tile are this over bands x W x 4 (at least 1), so that peak memory is a few times this, whatever
#: the frame's height and the cube's band count (a 4-band 20000-column frame: 104 rows; 121 bands: 3 rows)
TILE_BYTES = 32 * 2**20


def _check_tile_rows(tile_rows: int | None, shape: tuple[int, int, int] = (1, 1, 1)) -> int:
    """``tile_rows`` checked, or for None the rows of a ``(bands, H, W)`` cube that fill ``TILE_BYTES``."""
    if tile_rows is None:
        return max(1, TILE_BYTES // (4 * shape[0] * shape[2]))
    if isinstance(tile_rows, bool) or not isinstance(tile_rows, (int, np.integer)) or tile_rows < 1:
        raise ValueError(f"--tile-rows must be a positive whole number of rows, got {tile_rows!r}")
    return int(tile_rows)


class _EnviMaskRows:
    """An ENVI uint8 mask (one band, skin 255) with the input's ``map info`` and ``coordinate system string``,
    written rows by rows (``cubefiles.CubeWriter``)."""

    def __init__(self, out: StrPath, shape: tuple[int, int], envi_map: dict):
        from .cubefiles import CubeWriter

        self.rows = 0
        self._w = CubeWriter(out, (1, shape[0], shape[1]), "envi", None, quantity="skin mask", envi_extra=envi_map,
                             dtype=np.uint8)

    def write_rows(self, rows: np.ndarray) -> None:
        self._w.write_rows(self.rows, rows[None])
        self.rows += rows.shape[0]

    def close(self) -> None:
        self._w.close()

    def abort(self, exc: BaseException | None = None) -> None:
        self._w.abort(exc)


def _mask_writer(out: StrPath, shape: tuple[int, int], geotags: list, envi_map: dict | None = None) -> Any:
    """The mask's row writer by ``out``'s suffix: ``.png``; ``.tif`` (a GeoTIFF with the input's ``geotags``); or
    ``.hdr`` (ENVI, with an ENVI input's ``map info``). A georeferenced input's mask must keep its georeferencing:
    a GeoTIFF's in a ``.tif``, an ENVI header's ``map info`` in a ``.hdr`` (the two are not converted)."""
    from .cubefiles import PngRows, TiffMaskRows

    suf = os.path.splitext(str(out))[1].lower()
    mapped = bool(envi_map and "map info" in envi_map)
    if suf not in (".png", ".tif", ".tiff", ".hdr"):
        raise ValueError(f"--out {str(out)!r} must be a .png, .tif or ENVI .hdr mask")
    if mapped and suf != ".hdr":
        raise ValueError(f"--out {str(out)!r}: the ENVI cube is georeferenced (its header's 'map info'); give a .hdr "
                         "mask (an ENVI mask keeps its map info; a PNG or GeoTIFF mask here would drop it)")
    if geotags and suf not in (".tif", ".tiff"):
        raise ValueError(f"--out {str(out)!r}: the cube is georeferenced; give a .tif mask (a GeoTIFF keeps its "
                         "transform and CRS; a PNG or ENVI mask here would drop them)")
    if suf in (".tif", ".tiff"):
        return TiffMaskRows(out, shape[0], shape[1], geotags)
    if suf == ".hdr":
        return _EnviMaskRows(out, shape, dict(envi_map or {}))
    return PngRows(out, shape[0], shape[1])


def mask_rows(mask: np.ndarray) -> np.ndarray:
    """A boolean mask's rows as a mask file stores them: uint8, skin 255, not skin 0."""
    return np.asarray(mask, dtype=bool).view(np.uint8) * np.uint8(255)


def write_mask(out: StrPath, mask: ArrayLike, geotags: list | None = None, envi_map: dict | None = None) -> None:
    """A whole boolean (H, W) mask written by ``_mask_writer`` (the one way masks are written: ``detect_file``
    streams its rows through the same writers), atomically: ``.png``, ``.tif`` or ``.hdr`` by ``out``'s suffix."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ValueError(f"a mask must be (H, W), got shape {m.shape}")
    writer = _mask_writer(out, (m.shape[0], m.shape[1]), geotags or [], envi_map)
    try:
        writer.write_rows(mask_rows(m))
    except BaseException as e:
        writer.abort(e)
        raise
    writer.close()


def _finite_rows(cf: Any, r0: int, r1: int, where: str) -> np.ndarray:
    """``cf.read_rows(r0, r1)``, refused naming the file (``where``) when it holds NaN or infinite values (as
    ``load_cube`` refuses a cube read whole)."""
    block = cf.read_rows(r0, r1)
    if not (np.isfinite(block.min()) and np.isfinite(block.max())):  # NaN propagates through both
        raise ValueError(f"{where} holds NaN or infinite values")
    return block


def detect_file(det: OnboardDetector, cube: Any, config: ArrayLike, out: StrPath | None = None,
                tile_rows: int | None = None, negative: str = "error", min_reflectance: float | None = None,
                bands: Sequence[float] | None = None, option: str = "--cube",
                max_megapixels: float = MAX_MEGAPIXELS) -> dict:
    """Detect skin in a cube file of one frame (``cubefiles.open_cube``: ``.npy`` + sidecar, ENVI, GeoTIFF; or an
    open ``CubeFile``), ``tile_rows`` rows at a time (None: ``TILE_BYTES`` of the input): the model's bands read as they are or synthesised
    (``band_plan``; ``bands`` overrides the file's wavelengths; a cube without any must hold the model's four
    bands in its order), the mask written rows by rows to ``out`` (``_mask_writer``: ``.png``; ``.tif``, a GeoTIFF
    keeping a GeoTIFF input's georeferencing; ``.hdr``, ENVI keeping an ENVI input's map info) through a temporary file renamed at the end. The reflectance range is checked over
    the whole frame (``check_reflectance_range``, naming the file; a value above ``REFLECTANCE_CEILING`` too)
    before the rename: on refusal nothing is written. The mask
    equals ``det`` on the whole frame in memory. Returns ``skin_pixels``, ``pixels``, ``shape`` (H, W),
    ``out_of_domain``, ``plan`` ("reorder" or "synthesis"), ``clipped_values`` (with ``negative="clip"``) and
    ``reflectance_range``."""
    from .cubefiles import CubeFile, open_cube

    _check_tile_rows(tile_rows)
    cf = cube if isinstance(cube, CubeFile) else open_cube(cube, option, max_megapixels,
                                                            need_wavelengths=bands is None)
    nb, H, W = cf.shape
    tile_rows = _check_tile_rows(tile_rows, cf.shape)
    cube_bands = list(bands) if bands is not None else cf.bands
    where = f"{option} {str(cf.path)!r}"
    if cube_bands is not None and len(cube_bands) != nb:
        raise ValueError(f"--bands gives {len(cube_bands)} bands, but {where} holds {nb}")
    if cube_bands is None or not det.bands_nm:
        if nb != len(det.bands_nm or [0] * 4):
            raise ValueError(f"{where} holds {nb} bands and gives no wavelengths; the model needs its "
                             f"{len(det.bands_nm)} bands ({det.bands_nm} nm) in that order, or wavelengths to "
                             "pick or synthesise them from")
        plan: dict = {"kind": "reorder", "order": list(range(nb))}
    else:
        try:
            plan = band_plan(cube_bands, cf.fwhm, det.bands_nm, model_fwhm(det))
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
    c = np.asarray(config, dtype=np.float64).reshape(1, -1)
    writer = None if out is None else _mask_writer(out, (H, W), cf.geotags, cf.envi_map)
    low, high, over, skin, clipped = np.inf, -np.inf, 0, 0, 0
    ood = np.zeros(1, bool)
    try:
        for r0 in range(0, H, tile_rows):
            r1 = min(r0 + tile_rows, H)
            x = apply_plan(plan, _finite_rows(cf, r0, r1, where))
            t_lo, t_hi = float(x.min()), float(x.max())
            low, high = min(low, t_lo), max(high, t_hi)
            if t_hi > REFLECTANCE_MAX:
                over += int(np.count_nonzero(x > REFLECTANCE_MAX))
            res = det(x[None], c, negative=negative, min_reflectance=min_reflectance, range_check=False)
            m = res["mask"][0]
            skin += int(np.count_nonzero(m))
            ood = res["out_of_domain"]
            if "clipped_values" in res:
                clipped += int(res["clipped_values"][0])
            if writer is not None:
                writer.write_rows(mask_rows(m))
        check_reflectance_range(low, high, over / (4 * H * W), where)
    except BaseException as e:
        if writer is not None:
            writer.abort(e)
        raise
    if writer is not None:
        writer.close()
    doc = {"skin_pixels": skin, "pixels": H * W, "shape": [H, W], "out_of_domain": ood.tolist(),
           "plan": plan["kind"], "reflectance_range": [low, high]}
    if cube_bands is None and det.bands_nm:  # read as the model's bands, in its order: say so (a sidecar-less .npy)
        doc["bands_assumed"] = list(det.bands_nm)
    if negative == "clip":
        doc["clipped_values"] = [clipped]
    return doc


def calibrate_file(cube: Any, out: StrPath, panels: Sequence[tuple[Sequence[int], ArrayLike]] | None = None,
                   coefficients: tuple[ArrayLike, ArrayLike] | None = None, erode: int = 1,
                   tile_rows: int | None = None, option: str = "--cube",
                   max_megapixels: float = MAX_MEGAPIXELS) -> dict:
    """The empirical line of a signal cube file of one frame (``cubefiles.open_cube``), from reference
    ``panels`` (``elm_fit``'s (region, reflectance); only the panels' rows are read) or saved ``coefficients``
    (gain, offset), applied ``tile_rows`` rows at a time (None: ``TILE_BYTES`` of the input) and written to ``out`` in the input's format (``.npy`` +
    sidecar, ENVI, GeoTIFF with the input's geotags; wavelengths and FWHM carried over) through a temporary file
    renamed at the end; a tile with NaN or infinite reflectance removes it. Returns ``gain``, ``offset``, the fit
    (``signals``, ``references``, ``residual``; None with coefficients), ``shape``, ``reflectance_range`` and
    ``out`` (the path written)."""
    from .cubefiles import CubeFile, CubeWriter, open_cube, output_path

    _check_tile_rows(tile_rows)
    cf = cube if isinstance(cube, CubeFile) else open_cube(cube, option, max_megapixels)
    nb, H, W = cf.shape
    tile_rows = _check_tile_rows(tile_rows, cf.shape)
    where = f"{option} {str(cf.path)!r}"
    fit = None
    if coefficients is not None:
        gain, offset = (np.asarray(v, np.float64) for v in coefficients)
        if gain.shape != (nb,) or offset.shape != (nb,):
            raise ValueError(f"the coefficients give {gain.shape} gains and {offset.shape} offsets for a cube of "
                             f"{nb} bands")
    else:
        if panels is None or len(panels) < 2:
            raise ValueError(f"ELM needs at least 2 reference panels, got {0 if panels is None else len(panels)}")
        check_panel_regions([roi for roi, _ in panels])
        refs, sig = [], []
        for roi, rho in panels:
            y0, y1, x0, x1 = (int(v) for v in roi)
            if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
                raise ValueError(f"panel region {y0}:{y1}:{x0}:{x1} must satisfy 0 <= Y0 < Y1 <= {H} and "
                                 f"0 <= X0 < X1 <= {W}")
            refs.append(panel_reference(rho, nb))
            sig.append(panel_signal(_finite_rows(cf, y0, y1, where), (0, y1 - y0, x0, x1), erode))
        fit = elm_line(np.stack(refs), np.stack(sig))
        gain, offset = fit["gain"], fit["offset"]
    if not np.all(np.isfinite(gain)) or np.any(gain <= 0) or not np.all(np.isfinite(offset)):
        raise ValueError("gain must be finite and > 0 and offset finite in every band")
    dest = output_path(out, cf.format)
    low, high = np.inf, -np.inf
    with CubeWriter(dest, cf.shape, cf.format, cf.bands, cf.fwhm, "reflectance", cf.geotags,
                    {k: v for k, v in cf.envi_map.items()}) as w:
        for r0 in range(0, H, tile_rows):
            r1 = min(r0 + tile_rows, H)
            refl = elm_apply(_finite_rows(cf, r0, r1, where), gain, offset)
            t_lo, t_hi = float(refl.min()), float(refl.max())
            if not (np.isfinite(t_lo) and np.isfinite(t_hi)):
                raise ValueError("the calibrated cube holds NaN or infinite values (check the coefficients)")
            low, high = min(low, t_lo), max(high, t_hi)
            w.write_rows(r0, refl)
    return {"gain": gain, "offset": offset, "fit": fit, "shape": [nb, H, W], "reflectance_range": [low, high],
            "out": str(dest)}
