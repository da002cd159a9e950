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
from .boundaries import FEATURE_DOMAIN, FEATURE_UNITS, BoundaryModel
from .io import atomic_path

OPSET = 17
BANDS_NM = (544.0, 633.0, 1080.0, 1580.0)


class Detector(nn.Module):
    """Rules detector with configuration-dependent boxes. ``score`` is the signed distance (in index units)
    to the nearest box edge: positive inside; ``mask`` = score >= 0."""

    def __init__(self, boundaries: BoundaryModel):
        super().__init__()
        self.boundaries = boundaries

    def forward(self, cube: torch.Tensor, config: torch.Tensor):
        box = self.boundaries(config)[:, :, None, None]  # (B, 4, 1, 1)
        g, r, n, s = cube[:, 0], cube[:, 1], cube[:, 2], cube[:, 3]
        ndgri = (g - r) / (g + r)
        ndsi = (n - s) / (n + s)
        score = torch.minimum(torch.minimum(ndgri - box[:, 0], box[:, 1] - ndgri),
                              torch.minimum(ndsi - box[:, 2], box[:, 3] - ndsi))
        score = torch.where(torch.isnan(score), torch.full_like(score, -1.0), score)
        return score >= 0, score


def metadata(model: BoundaryModel, manifest_sha256: str = "") -> dict[str, str]:
    return {
        "torchskin_version": __version__,
        "bands_nm": json.dumps(list(BANDS_NM)),
        "band_units": "nm; reflectance in [0, 1] (ELM-calibrated)",
        "features": json.dumps(list(model.features)),
        "feature_units": json.dumps([FEATURE_UNITS.get(f, "") for f in model.features]),
        "feature_domain": json.dumps([list(FEATURE_DOMAIN.get(f, (-1e30, 1e30))) for f in model.features]),
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


def export(model: BoundaryModel, out_dir, manifest_sha256: str = "") -> dict:
    """Write ``boundaries.onnx`` and ``detector.onnx`` into ``out_dir``; return their paths."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    meta = metadata(model, manifest_sha256)
    k = len(model.features)
    cfg = torch.zeros(2, k)
    _to_onnx(model, (cfg,), ["config"], ["boxes"], {"config": {0: "N"}, "boxes": {0: "N"}}, meta,
             out / "boundaries.onnx")
    cube = torch.full((2, 4, 3, 5), 0.3)
    _to_onnx(Detector(model), (cube, cfg), ["cube", "config"], ["mask", "score"],
             {"cube": {0: "B", 2: "H", 3: "W"}, "config": {0: "B"}, "mask": {0: "B", 1: "H", 2: "W"},
              "score": {0: "B", 1: "H", 2: "W"}}, meta, out / "detector.onnx")
    return {"boundaries": str(out / "boundaries.onnx"), "detector": str(out / "detector.onnx")}
