"""The ``boxes`` kind's ONNX export: the export copy of a model (``folded``), ``boundaries.onnx``
(``boundaries_graph``) and ``detector.onnx`` (``edge_detector_graph``: the five edge forms ``edge_matrix``, whose
torch reference is ``BoxDetector``). Takes a ``BoxModel`` but constructs none (``model`` imports this module)."""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

import numpy as np
import torch
from torch import nn

from ..graphs import add_metadata, torch_graph

if TYPE_CHECKING:
    import onnx

    from .. import boxes


def folded(model: boxes.BoxModel) -> boxes.BoxModel:
    """A copy of ``model`` for export, the same function with fewer graph nodes: the feature standardisation
    folded into the first linear layer, and d1 (the NDVN rule) carried by a fifth output of the last layer
    (zero weights, bias d1) instead of being added to the boxes."""
    import copy

    m = copy.deepcopy(model).eval()
    first = cast(nn.Linear, m.net[0])
    with torch.no_grad():
        w = first.weight / m.std
        first.bias.sub_(w @ m.mean)
        first.weight.copy_(w)
        last = cast(nn.Linear, m.net[-1])
        if last.out_features == 5:  # d1 is already the fifth output (``ndvn_head``)
            m.standardize = False
            return m
        packed = nn.Linear(last.in_features, 5)
        packed.weight.zero_()
        packed.weight[:4] = last.weight
        packed.bias[:4] = last.bias
        packed.bias[4] = m.ndvn_min
        m.net[-1] = packed
    m.standardize = False
    return m


#: the edge forms as a linear function of the box: W(box) = box @ EDGE_M + EDGE_C, reshaped to (5 edges, 4 bands)
#: with bands (g, r, n, s) = (544, 633, 1080, 1580) nm and edges::
#:
#:   L1 = (g - r) - b1 (g + r),  L2 = b2 (g + r) - (g - r),  L3 = (n - s) - c1 (n + s),  L4 = c2 (n + s) - (n - s),
#:   L5 = (g + r) - (n + s) - d1 (g + r + n + s)   (the visible/NIR rule NDVN >= d1)
EDGE_C = ((1.0, -1.0, 0.0, 0.0), (-1.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, -1.0), (0.0, 0.0, -1.0, 1.0),
          (1.0, 1.0, -1.0, -1.0))
EDGE_M = tuple(tuple(float(v) for v in row) for row in (
    [-1, -1, 0, 0] + [0] * 16, [0] * 4 + [1, 1, 0, 0] + [0] * 12, [0] * 10 + [-1, -1] + [0] * 8,
    [0] * 14 + [1, 1] + [0] * 4, [0] * 16 + [-1, -1, -1, -1]))


def edge_matrix(boxes: torch.Tensor) -> torch.Tensor:
    """(B, E) boxes (E = 4: b1, b2, c1, c2; E = 5 with d1) -> (B, E, 4) matrices whose rows, applied to a
    pixel's (g, r, n, s), give the edge forms L1..LE: each is the pixel's index margin to that edge times its
    band sum (g + r, n + s, or g + r + n + s for the NDVN rule)."""
    e = boxes.shape[1]
    M = torch.tensor(EDGE_M, dtype=boxes.dtype, device=boxes.device)[:e, :4 * e]
    C = torch.tensor(EDGE_C, dtype=boxes.dtype, device=boxes.device)[:e].reshape(4 * e)
    return (boxes @ M + C).reshape(-1, e, 4)


class BoxDetector(nn.Module):
    """Rules detector with configuration-dependent boxes, written without divisions (the torch reference of
    ``detector.onnx`` for a box model; ``classifier.ClassifierDetector`` is the classifier's):
    NDGRI in [b1, b2], NDSI in [c1, c2] and NDVN >= d1 <=> the five edge forms L1..L5 (``edge_matrix``) are
    positive. ``score`` = min(L1..L5): the smallest index margin to a box edge, weighted by the band sum
    (g + r, n + s or g + r + n + s), in reflectance units; positive inside. ``mask`` = score > 0 (a pixel with
    g + r = 0 or n + s = 0 has undefined indices and is never skin). This module is the reference;
    ``edge_detector_graph`` writes the same arithmetic as a short ONNX graph (one one-row MatMul per edge, Min,
    Greater)."""

    def __init__(self, model: boxes.BoxModel):
        super().__init__()
        self.model = model

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mask and score (B, H, W) of a reflectance cube (B, 4, H, W) under configurations (B, k)."""
        B, _, H, W = cube.shape
        lin = edge_matrix(self.model(config)) @ cube.reshape(B, 4, H * W)  # (B, E, HW)
        score = lin.amin(1).reshape(B, H, W)
        return score > 0, score


def boundaries_graph(model: boxes.BoxModel, meta: dict[str, str]) -> onnx.ModelProto:
    """The ONNX graph configuration (N, k) -> boxes (N, 5) of a box model (its ``folded`` copy)."""
    cfg = torch.zeros(2, len(model.features))
    return torch_graph(folded(model.eval()), (cfg,), ["config"], ["boxes"], {"config": {0: "N"}, "boxes": {0: "N"}},
                       meta)


def edge_detector_graph(boundaries_model: onnx.ModelProto, meta: dict[str, str]) -> onnx.ModelProto:
    """``detector.onnx`` from the exported ``boundaries.onnx`` graph (boxes (N, E), E = 4 or 5) plus a
    hand-written head: the edge matrices from the boxes (MatMul, Add, Reshape), then per pixel one one-row
    MatMul per edge form (viewed as (B, H, W)) -> Min -> Greater."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from ... import __version__

    g = boundaries_model.graph
    box = g.output[0].name
    e = int(g.output[0].type.tensor_type.shape.dim[1].dim_value) or 5
    inits = list(g.initializer) + [
        numpy_helper.from_array(np.array(EDGE_M, dtype=np.float32)[:e, :4 * e], "det_edge_M"),
        numpy_helper.from_array(np.array(EDGE_C, dtype=np.float32)[:e].reshape(4 * e), "det_edge_C"),
        numpy_helper.from_array(np.array([-1, e, 4], dtype=np.int64), "det_w_shape"),
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
        helper.make_node("Split", ["det_w"], [f"det_w{k}" for k in range(e)], axis=1),
    ]
    for k in range(e):  # one edge form per MatMul, viewed as (B, H, W): no (B, E, HW) intermediate to split
        head += [helper.make_node("MatMul", [f"det_w{k}", "det_flat"], [f"det_e{k}"]),
                 helper.make_node("Reshape", [f"det_e{k}", "det_bhw"], [f"det_l{k}"])]
    head += [helper.make_node("Min", [f"det_l{k}" for k in range(e)], ["score"]),
             helper.make_node("Greater", ["score", "det_zero"], ["mask"])]
    cube = helper.make_tensor_value_info("cube", TensorProto.FLOAT, ["B", 4, "H", "W"])
    outputs = [helper.make_tensor_value_info("mask", TensorProto.BOOL, ["B", "H", "W"]),
               helper.make_tensor_value_info("score", TensorProto.FLOAT, ["B", "H", "W"])]
    graph = helper.make_graph(list(g.node) + head, "torchskin_detector", [cube] + list(g.input), outputs, inits)
    m = helper.make_model(graph, opset_imports=list(boundaries_model.opset_import),
                          producer_name="torchskin", producer_version=__version__)
    m.ir_version = boundaries_model.ir_version
    add_metadata(m, meta)
    onnx.checker.check_model(m, full_check=True)
    return m


__all__ = ["EDGE_C", "EDGE_M", "BoxDetector", "boundaries_graph", "edge_detector_graph", "edge_matrix", "folded"]
