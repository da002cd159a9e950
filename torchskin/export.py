"""Export learned detectors to ONNX: ``boundaries.onnx`` and ``baseline_box.onnx`` (configuration (N, k) ->
boxes (N, 4)) and ``detector.onnx`` (reflectance cube (B, 4, H, W) + configuration (B, k) -> mask (B, H, W) and
score; from a box model or a classifier), opset 17, with metadata (band centres, units, feature order and
units, skin surface model, training manifest hash, package version)."""

from __future__ import annotations

import io
import json
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, cast

import torch
from torch import nn

from . import __version__
from .bands import INDEX_BANDS_NM
from .boundaries import BOX_ORDER, FEATURE_UNITS, BoundaryModel, folded
from .io import atomic_path

if TYPE_CHECKING:
    import onnx

    from .classifier import SkinClassifier

OPSET = 17


#: the edge forms as a linear function of the box: W(box) = box @ EDGE_M + EDGE_C, reshaped to (5 edges, 4 bands)
#: with bands (g, r, n, s) = (544, 633, 1080, 1580) nm and edges
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
    ``detector.onnx`` for a box model; ``ClassifierDetector`` is the classifier's):
    NDGRI in [b1, b2], NDSI in [c1, c2] and NDVN >= d1 <=> the five edge forms L1..L5 (``edge_matrix``) are
    positive. ``score`` = min(L1..L5): the smallest index margin to a box edge, weighted by the band sum
    (g + r, n + s or g + r + n + s), in reflectance units; positive inside. ``mask`` = score > 0 (a pixel with
    g + r = 0 or n + s = 0 has undefined indices and is never skin). This module is the reference; ``export``
    writes the same arithmetic as a short ONNX graph (one one-row MatMul per edge, Min, Greater)."""

    def __init__(self, boundaries: BoundaryModel):
        super().__init__()
        self.boundaries = boundaries

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mask and score (B, H, W) of a reflectance cube (B, 4, H, W) under configurations (B, k)."""
        B, _, H, W = cube.shape
        lin = edge_matrix(self.boundaries(config)) @ cube.reshape(B, 4, H * W)  # (B, E, HW)
        score = lin.amin(1).reshape(B, H, W)
        return score > 0, score


def metadata(model: BoundaryModel | SkinClassifier, manifest_sha256: str = "", surface: str = "") -> dict[str, str]:
    """The ONNX metadata of an exported model (a ``BoundaryModel`` or a ``classifier.SkinClassifier``): band
    centres and units, feature order, units and domain, box order, NDVN formula, skin surface model, training
    manifest hash, package version (every key is part of the shipped files: keep them as they are)."""
    return {
        "skin_surface_model": surface,
        "torchskin_version": __version__,
        "bands_nm": json.dumps(list(INDEX_BANDS_NM)),
        "band_units": "nm; reflectance in [0, 1] (ELM-calibrated)",
        "features": json.dumps(list(model.features)),
        "feature_units": json.dumps([FEATURE_UNITS.get(f, "") for f in model.features]),
        "feature_domain": json.dumps([[float(lo), float(hi)] for lo, hi in model.domain.tolist()]),
        "box_order": json.dumps(list(BOX_ORDER)),
        "ndvn": "((g + r) - (n + s)) / (g + r + n + s) with (g, r, n, s) the 544, 633, 1080, 1580 nm reflectance",
        "training_manifest_sha256": manifest_sha256,
    }


def _detector_graph(boundaries_model, meta: dict):
    """``detector.onnx`` from the exported ``boundaries.onnx`` graph (boxes (N, E), E = 4 or 5) plus a
    hand-written head: the edge matrices from the boxes (MatMul, Add, Reshape), then per pixel one one-row
    MatMul per edge form (viewed as (B, H, W)) -> Min -> Greater."""
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

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
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.checker.check_model(m, full_check=True)
    return m


class ClassifierDetector(nn.Module):
    """``detector.onnx`` for a ``classifier.SkinClassifier``: cube (B, 4, H, W) + configuration (B, k) -> mask
    and score (B, H, W), score = logit - threshold (positive: skin). The configuration's part of the first
    layer (and of the linear part) is computed once per frame; per pixel the three band ratios go through the MLP
    and the linear part."""

    def __init__(self, classifier: SkinClassifier):
        super().__init__()
        self.c = classifier

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mask and score (B, H, W) of a reflectance cube (B, 4, H, W) under configurations (B, k)."""
        from .classifier import ratio_features

        B, _, H, W = cube.shape
        x = cube.reshape(B, 4, H * W).transpose(1, 2)  # (B, HW, 4)
        first, *rest = list(self.c.net)
        first = cast(nn.Linear, first)
        w = first.weight
        cfg = (config - self.c.mean) / self.c.std  # (B, k)
        bias = cfg @ w[:, 3:].T + first.bias  # (B, hidden): the configuration's part, once per frame
        feats = ratio_features(x) * 2.0
        h = feats @ w[:, :3].T + bias[:, None, :]
        for layer in rest:
            h = layer(h)
        lw, lb = self.c.linear.weight[0], self.c.linear.bias  # the linear part, its configuration term per frame
        h = h.squeeze(-1) + feats @ lw[:3] + (cfg @ lw[3:] + lb)[:, None]
        valid = (x[..., 0] + x[..., 1] > 0) & (x[..., 2] + x[..., 3] > 0)
        score = (h - self.c.threshold).reshape(B, H, W)
        return (score > 0) & valid.reshape(B, H, W), score


def _onnx_bytes(module, args, input_names, output_names, dynamic_axes, meta: dict):
    import onnx

    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter is deliberate: no onnxscript dependency
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(module, args, buf, input_names=input_names, output_names=output_names,  # type: ignore[arg-type]
                          dynamic_axes=dynamic_axes, opset_version=OPSET, dynamo=False)
    m = onnx.load_from_string(buf.getvalue())
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.checker.check_model(m)
    return m


def boundaries_graph(model: BoundaryModel, meta: dict[str, str]) -> onnx.ModelProto:
    """The ONNX graph configuration (N, k) -> boxes (N, 4) of a box model."""
    cfg = torch.zeros(2, len(model.features))
    return _onnx_bytes(folded(model.eval()), (cfg,), ["config"], ["boxes"], {"config": {0: "N"}, "boxes": {0: "N"}},
                       meta)


def detector_graph(model: BoundaryModel | SkinClassifier, meta: dict[str, str]) -> onnx.ModelProto:
    """The ONNX graph cube (B, 4, H, W) + configuration (B, k) -> mask, score of a box model (edge forms) or a
    classifier."""
    from .classifier import SkinClassifier

    if isinstance(model, SkinClassifier):
        cube, cfg = torch.rand(2, 4, 3, 5), torch.zeros(2, len(model.features))
        axes = {"cube": {0: "B", 2: "H", 3: "W"}, "config": {0: "B"}, "mask": {0: "B", 1: "H", 2: "W"},
                "score": {0: "B", 1: "H", 2: "W"}}
        return _onnx_bytes(ClassifierDetector(model.eval()), (cube, cfg), ["cube", "config"], ["mask", "score"], axes,
                           meta)
    return _detector_graph(boundaries_graph(model, {}), meta)


def export(model: BoundaryModel, out_dir: str | os.PathLike, manifest_sha256: str = "", *, surface: str = "",
           baseline: BoundaryModel | None = None, detector: BoundaryModel | SkinClassifier | None = None,
           detector_meta: dict[str, str] | None = None,
           checkpoints: dict[str, str] | None = None) -> dict[str, str]:
    """Write ``boundaries.onnx`` (``model``), ``baseline_box.onnx`` (``baseline``, a constant box with the same
    inputs and outputs, when given) and ``detector.onnx`` (``detector``: a box model or a classifier; default
    ``model``) into ``out_dir``, opset 17, with metadata (``metadata``). Every graph is built and checked before
    any file is written; each file is written atomically. The same models give the same bytes.

    Args:
        model: the box model of ``boundaries.onnx`` (and of ``detector.onnx`` by default).
        out_dir: the output folder (created if missing).
        manifest_sha256: the training dataset's manifest hash, recorded in the metadata.
        surface: the skin surface model of the training renders ("thesis" or "conserving"), recorded likewise.
        baseline: a constant box model for ``baseline_box.onnx`` (none written without it).
        detector: the model behind ``detector.onnx``: a ``BoundaryModel`` or a ``classifier.SkinClassifier``.
        detector_meta: extra metadata of ``detector.onnx`` (e.g. which model it is and why).
        checkpoints: per graph name ("boundaries", "baseline_box", "detector"), the checkpoint it came from
            (metadata key ``checkpoint``).

    Shape:
        boundaries.onnx / baseline_box.onnx: ``config`` (N, k) -> ``boxes`` (N, 5); detector.onnx: ``cube``
        (B, 4, H, W) and ``config`` (B, k) -> ``mask`` bool and ``score`` float32, (B, H, W).

    Returns:
        ``{name: path}`` of the files written ("boundaries", "detector" and, with ``baseline``,
        "baseline_box").
    """
    model = model.eval()
    ck = checkpoints or {}

    def meta(m, name):
        return {**metadata(m, manifest_sha256, surface), **({"checkpoint": ck[name]} if name in ck else {})}

    graphs = {"boundaries": boundaries_graph(model, meta(model, "boundaries"))}
    if baseline is not None:
        graphs["baseline_box"] = boundaries_graph(baseline, meta(baseline, "baseline_box"))
    det = model if detector is None else detector
    graphs["detector"] = detector_graph(det, {**meta(det, "detector"), **(detector_meta or {})})
    return write_graphs(graphs, Path(out_dir))


def write_graphs(graphs: dict, out: str | os.PathLike) -> dict[str, str]:
    """Write ``{name: onnx.ModelProto}`` as ``out/<name>.onnx`` (atomically, one by one)."""
    import onnx

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, g in graphs.items():
        with atomic_path(out / f"{name}.onnx", suffix=".onnx") as tmp:
            onnx.save(g, str(tmp))
        paths[name] = str(out / f"{name}.onnx")
    return paths


def write_model_cards(out_dir: str | os.PathLike, train: dict, evaluation: dict | None = None,
                      trains: dict | None = None) -> dict[str, str]:
    """A Markdown card beside each exported model (``boundaries``, ``baseline_box``, ``detector``; metadata read
    back from the ONNX files). ``train``: the training summary of boundaries.onnx; ``trains``: per model name,
    its own (default ``train``)."""
    import onnx

    from .io import write_text
    from .modelcard import model_card

    out = Path(out_dir)
    cards = {}
    for kind in ("boundaries", "baseline_box", "detector"):
        if not (out / f"{kind}.onnx").is_file():
            continue
        meta = {p.key: p.value for p in onnx.load(str(out / f"{kind}.onnx")).metadata_props}
        cards[kind] = model_card(kind, meta, (trains or {}).get(kind, train), evaluation)
    paths = {}
    for kind, text in cards.items():  # every card rendered before any is written
        write_text(out / f"{kind}.md", text)
        paths[f"{kind}_card"] = str(out / f"{kind}.md")
    return paths
