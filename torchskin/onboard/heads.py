"""The heads an ``OnboardDetector`` runs its graph on (``detector_head``): the box head, a box detector graph split
into its per-frame part and a per-pixel head rebuilt for tiles (``_split_box_graph``, ``_EdgeHead``), or the
generic head, any other graph as it is. numpy, onnxruntime and (for the box head) onnx; no torch."""

from __future__ import annotations

from typing import Any

import numpy as np

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


def detector_head(meta: dict[str, str], path: str, options: Any) -> tuple[str, Any]:
    """The head an ``OnboardDetector`` runs its graph on, chosen by the graph's metadata ``kind``: ``"boxes"`` (a
    kind of ``BOX_HEAD_KINDS``: the box head, ``_split_box_graph``'s per-frame session and tile head), ``"lut"``
    (metadata ``onboard_head`` "lut": the table looked up with numpy, ``onboard.lut.LutHead``) or ``"generic"``
    (any other kind: the graph as it is, per tile), and the head's parts (None for the generic head). A graph without ``kind`` (exported before graphs recorded it) is told by today's node names instead
    (``_edges_by_name``: the Split of ``det_w``); a box graph whose edges are not found runs on the generic head
    (the same results, slower). A kind's graph may name its head in the metadata ``onboard_head`` (written by
    ``export.metadata`` where the kind asks for another head than ``BOX_HEAD_KINDS`` gives it), which wins."""
    kind = meta.get("kind")
    head = meta.get("onboard_head") or ("boxes" if kind is None or kind in BOX_HEAD_KINDS else "generic")
    if head == "lut":  # a lookup table (``onboard.lut``), found by its metadata and its bit table
        from .lut import lut_head

        table = lut_head(path, meta)
        return ("generic", None) if table is None else ("lut", table)
    if head != "boxes":
        return "generic", None
    split = _split_box_graph(path, options, by_name=kind is None)
    return ("generic", None) if split is None else ("boxes", split)


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
