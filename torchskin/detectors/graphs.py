"""ONNX helpers for the kinds' exported graphs: the opset, a torch module exported to a checked ``onnx.ModelProto``
with metadata (``torch_graph``), and metadata written onto a graph (``add_metadata``)."""

from __future__ import annotations

import io
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

if TYPE_CHECKING:
    import onnx

#: the ONNX opset of every exported graph
OPSET = 17


def add_metadata(m: onnx.ModelProto, meta: dict[str, str]) -> None:
    """Append ``meta`` to the graph's metadata properties, in order."""
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v


def torch_graph(module: nn.Module, args: tuple[Any, ...], input_names: Sequence[str], output_names: Sequence[str],
                dynamic_axes: dict[str, dict[int, str]], meta: dict[str, str]) -> onnx.ModelProto:
    """``module`` called on ``args`` as an ONNX graph (opset ``OPSET``, the TorchScript exporter: no onnxscript
    dependency), with the given input and output names, dynamic axes and metadata; checked."""
    import onnx

    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter is deliberate: no onnxscript dependency
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(module, args, buf, input_names=list(input_names),  # type: ignore[arg-type]
                          output_names=list(output_names), dynamic_axes=dynamic_axes, opset_version=OPSET,
                          dynamo=False)
    m = onnx.load_from_string(buf.getvalue())
    add_metadata(m, meta)
    onnx.checker.check_model(m)
    return m


#: the dynamic axes of a detector graph (cube, config -> mask, score)
DETECTOR_AXES = {"cube": {0: "B", 2: "H", 3: "W"}, "config": {0: "B"}, "mask": {0: "B", 1: "H", 2: "W"},
                 "score": {0: "B", 1: "H", 2: "W"}}


def torch_detector_graph(module: nn.Module, k: int, meta: dict[str, str], n_bands: int = 4) -> onnx.ModelProto:
    """The detector graph of a torch module ``module(cube (B, n_bands, H, W), config (B, k)) -> (mask, score)``: inputs
    ``cube`` and ``config``, outputs ``mask`` and ``score``, batch and image axes dynamic. A module that ignores the
    configuration still gets the ``config`` input (unused: the exporter drops it, the onboard runtime feeds it)."""
    import onnx
    from onnx import TensorProto, helper

    cube, cfg = torch.rand(2, n_bands, 3, 5), torch.zeros(2, k)
    m = torch_graph(module, (cube, cfg), ["cube", "config"], ["mask", "score"], DETECTOR_AXES, meta)
    if "config" not in {i.name for i in m.graph.input}:
        m.graph.input.append(helper.make_tensor_value_info("config", TensorProto.FLOAT, ["B", k]))
        onnx.checker.check_model(m)
    return m


__all__ = ["DETECTOR_AXES", "OPSET", "add_metadata", "torch_detector_graph", "torch_graph"]
