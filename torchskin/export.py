"""Export learned boundaries to ONNX: ``boundaries.onnx`` (configuration (N, k) -> boxes (N, 4)) and
``detector.onnx`` (reflectance cube (B, 4, H, W) + configuration (B, k) -> mask (B, H, W) and score), opset
17, with metadata (band centres, units, feature order and units, training manifest hash, package version)."""

from __future__ import annotations

import io
import json
import warnings

import torch
from torch import nn

from . import __version__
from .boundaries import FEATURE_UNITS, BoundaryModel, folded
from .io import atomic_path

OPSET = 17
BANDS_NM = (544.0, 633.0, 1080.0, 1580.0)


#: the edge forms as a linear function of the box: W(box) = box @ EDGE_M + EDGE_C, reshaped to (4 edges, 4 bands)
#: with bands (g, r, n, s) = (544, 633, 1080, 1580) nm and edges
#:   L1 = (g - r) - b1 (g + r),  L2 = b2 (g + r) - (g - r),  L3 = (n - s) - c1 (n + s),  L4 = c2 (n + s) - (n - s)
EDGE_C = ((1.0, -1.0, 0.0, 0.0), (-1.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, -1.0), (0.0, 0.0, -1.0, 1.0))
EDGE_M = tuple(tuple(float(v) for v in row) for row in (
    [-1, -1, 0, 0] + [0] * 12, [0] * 4 + [1, 1, 0, 0] + [0] * 8, [0] * 10 + [-1, -1] + [0] * 4, [0] * 14 + [1, 1]))


def edge_matrix(boxes: torch.Tensor) -> torch.Tensor:
    """(B, 4) boxes -> (B, 4, 4) matrices whose rows, applied to a pixel's (g, r, n, s), give the four edge
    forms L1..L4: each is the pixel's index margin to that edge times its band-pair sum."""
    M = torch.tensor(EDGE_M, dtype=boxes.dtype, device=boxes.device)
    C = torch.tensor(EDGE_C, dtype=boxes.dtype, device=boxes.device).reshape(16)
    return (boxes @ M + C).reshape(-1, 4, 4)


class Detector(nn.Module):
    """Rules detector with configuration-dependent boxes, written without divisions:
    NDGRI in [b1, b2] and NDSI in [c1, c2] <=> the four edge forms L1..L4 (``edge_matrix``) are positive.
    ``score`` = min(L1..L4): the smallest index margin to a box edge, weighted by the band-pair sum (g + r
    or n + s), in reflectance units; positive inside. ``mask`` = score > 0 (a pixel with g + r = 0 or
    n + s = 0 has undefined indices and is never skin). This module is the reference; ``export`` writes the
    same arithmetic as a short ONNX graph (four one-row MatMuls, Min, Greater)."""

    def __init__(self, boundaries: BoundaryModel):
        super().__init__()
        self.boundaries = boundaries

    def forward(self, cube: torch.Tensor, config: torch.Tensor):
        B, _, H, W = cube.shape
        lin = edge_matrix(self.boundaries(config)) @ cube.reshape(B, 4, H * W)
        score = lin.amin(1).reshape(B, H, W)
        return score > 0, score


def metadata(model: BoundaryModel, manifest_sha256: str = "") -> dict[str, str]:
    return {
        "torchskin_version": __version__,
        "bands_nm": json.dumps(list(BANDS_NM)),
        "band_units": "nm; reflectance in [0, 1] (ELM-calibrated)",
        "features": json.dumps(list(model.features)),
        "feature_units": json.dumps([FEATURE_UNITS.get(f, "") for f in model.features]),
        "feature_domain": json.dumps([[float(lo), float(hi)] for lo, hi in model.domain.tolist()]),
        "box_order": json.dumps(["b1_ndgri_min", "b2_ndgri_max", "c1_ndsi_min", "c2_ndsi_max"]),
        "training_manifest_sha256": manifest_sha256,
    }


def _to_onnx(module, args, input_names, output_names, dynamic_axes, meta: dict, path) -> None:
    import onnx

    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter is deliberate: no onnxscript dependency
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(module, args, buf, input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes, opset_version=OPSET, dynamo=False)
    m = onnx.load_from_string(buf.getvalue())
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.checker.check_model(m)
    with atomic_path(path, suffix=".onnx") as tmp:
        onnx.save(m, str(tmp))


def _detector_graph(boundaries_model, meta: dict):
    """``detector.onnx`` from the exported ``boundaries.onnx`` graph plus a hand-written head: the edge
    matrices from the boxes (MatMul, Add, Reshape), then per pixel four one-row MatMuls (one per edge form,
    viewed as (B, H, W)) -> Min -> Greater."""
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    g = boundaries_model.graph
    box = g.output[0].name
    inits = list(g.initializer) + [
        numpy_helper.from_array(np.array(EDGE_M, dtype=np.float32), "det_edge_M"),
        numpy_helper.from_array(np.array(EDGE_C, dtype=np.float32).reshape(16), "det_edge_C"),
        numpy_helper.from_array(np.array([-1, 4, 4], dtype=np.int64), "det_w_shape"),
        numpy_helper.from_array(np.array([0, 4, -1], dtype=np.int64), "det_flat_shape"),
        numpy_helper.from_array(np.array([0, 2, 3], dtype=np.int64), "det_bhw_index"),
        numpy_helper.from_array(np.array(0.0, dtype=np.float32), "det_zero"),
    ]
    head = [
        helper.make_node("MatMul", [box, "det_edge_M"], ["det_wm"]),
        helper.make_node("Add", ["det_wm", "det_edge_C"], ["det_wflat"]),
        helper.make_node("Reshape", ["det_wflat", "det_w_shape"], ["det_w"]),
        helper.make_node("Shape", ["cube"], ["det_cube_shape"]),
        helper.make_node("Gather", ["det_cube_shape", "det_bhw_index"], ["det_bhw"]),
        helper.make_node("Reshape", ["cube", "det_flat_shape"], ["det_flat"]),
        helper.make_node("Split", ["det_w"], [f"det_w{k}" for k in range(4)], axis=1),
    ]
    for k in range(4):  # one edge form per MatMul, viewed as (B, H, W): no (B, 4, HW) intermediate to split
        head += [helper.make_node("MatMul", [f"det_w{k}", "det_flat"], [f"det_e{k}"]),
                 helper.make_node("Reshape", [f"det_e{k}", "det_bhw"], [f"det_l{k}"])]
    head += [helper.make_node("Min", [f"det_l{k}" for k in range(4)], ["score"]),
             helper.make_node("Greater", ["score", "det_zero"], ["mask"])]
    cube = helper.make_tensor_value_info("cube", TensorProto.FLOAT, ["B", 4, "H", "W"])
    outputs = [helper.make_tensor_value_info("mask", TensorProto.BOOL, ["B", "H", "W"]),
               helper.make_tensor_value_info("score", TensorProto.FLOAT, ["B", "H", "W"])]
    graph = helper.make_graph(list(g.node) + head, "torchskin_detector", [cube] + list(g.input), outputs, inits)
    m = helper.make_model(graph, opset_imports=list(boundaries_model.opset_import),
                          producer_name="torchskin", producer_version=__version__)
    m.ir_version = boundaries_model.ir_version
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.checker.check_model(m, full_check=True)
    return m


def export(model: BoundaryModel, out_dir, manifest_sha256: str = "") -> dict:
    """Write ``boundaries.onnx`` and ``detector.onnx`` into ``out_dir``; return their paths."""
    from pathlib import Path

    import onnx

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    meta = metadata(model, manifest_sha256)
    k = len(model.features)
    cfg = torch.zeros(2, k)
    _to_onnx(folded(model), (cfg,), ["config"], ["boxes"], {"config": {0: "N"}, "boxes": {0: "N"}}, meta,
             out / "boundaries.onnx")
    det = _detector_graph(onnx.load(str(out / "boundaries.onnx")), meta)
    with atomic_path(out / "detector.onnx", suffix=".onnx") as tmp:
        onnx.save(det, str(tmp))
    return {"boundaries": str(out / "boundaries.onnx"), "detector": str(out / "detector.onnx")}


def write_model_cards(out_dir, train: dict, evaluation: dict | None = None) -> dict:
    """``boundaries.md`` and ``detector.md`` beside the exported models (metadata read back from them)."""
    from pathlib import Path

    import onnx

    from .io import write_text
    from .modelcard import model_card

    out = Path(out_dir)
    paths = {}
    for kind in ("boundaries", "detector"):
        meta = {p.key: p.value for p in onnx.load(str(out / f"{kind}.onnx")).metadata_props}
        write_text(out / f"{kind}.md", model_card(kind, meta, train, evaluation))
        paths[f"{kind}_card"] = str(out / f"{kind}.md")
    return paths
