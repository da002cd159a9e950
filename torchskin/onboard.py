"""Onboard runtime: load the exported ONNX models and run them with numpy and onnxruntime only (no torch).

    det = Detector("exports/detector.onnx")
    out = det(cube, config)      # cube (B, 4, H, W) float32 reflectance, config (B, k) in the model's units
    out["mask"], out["score"], out["out_of_domain"]

Inputs are validated: wrong rank, band count or dtype, NaN or negative reflectance raise ``ValueError``;
configurations outside the training domain are flagged per frame in ``out_of_domain`` (never silently used).
"""

from __future__ import annotations

import json

import numpy as np


class _Model:
    def __init__(self, path):
        import onnxruntime as ort

        self.path = str(path)
        try:
            self.session = ort.InferenceSession(self.path, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types
            raise ValueError(f"cannot load ONNX model {self.path!r}: {e}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        self.meta = dict(meta)
        self.features = json.loads(meta.get("features", "[]"))
        self.domain = np.array(json.loads(meta.get("feature_domain", "[]")), dtype=np.float64).reshape(-1, 2)
        self.bands_nm = json.loads(meta.get("bands_nm", "[]"))

    def _config(self, config) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(config)
        if c.ndim == 1:
            c = c[None]
        if c.ndim != 2 or c.shape[1] != len(self.features):
            raise ValueError(f"config must be (N, {len(self.features)}) with features {self.features}, got {c.shape}")
        if not np.issubdtype(c.dtype, np.floating):
            raise ValueError(f"config must be floating point, got {c.dtype}")
        if not np.isfinite(c).all():
            raise ValueError("config holds NaN or infinite values")
        c = c.astype(np.float32)
        ood = ((c < self.domain[:, 0]) | (c > self.domain[:, 1])).any(1) if len(self.domain) else np.zeros(len(c), bool)
        return c, ood


class Boundaries(_Model):
    """``boundaries.onnx``: configuration (N, k) -> boxes (N, 4) (b1, b2, c1, c2)."""

    def __call__(self, config) -> dict:
        c, ood = self._config(config)
        (boxes,) = self.session.run(None, {"config": c})
        return {"boxes": boxes, "out_of_domain": ood}


class Detector(_Model):
    """``detector.onnx``: reflectance cube (B, 4, H, W) + configuration (B, k) -> mask and score."""

    def __call__(self, cube, config) -> dict:
        x = np.asarray(cube)
        if x.ndim != 4:
            raise ValueError(f"cube must have rank 4 (B, bands, H, W), got shape {x.shape}")
        if x.shape[1] != len(self.bands_nm or [0] * 4):
            raise ValueError(f"cube must have {len(self.bands_nm)} bands ({self.bands_nm} nm) on axis 1, "
                             f"got {x.shape[1]}")
        if x.dtype != np.float32:
            raise ValueError(f"cube must be float32 reflectance, got {x.dtype}")
        if np.isnan(x).any():
            raise ValueError("cube holds NaN reflectance")
        if (x < 0).any():
            raise ValueError("cube holds negative reflectance")
        c, ood = self._config(config)
        if c.shape[0] != x.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for a batch of {x.shape[0]} frames")
        mask, score = self.session.run(None, {"cube": np.ascontiguousarray(x), "config": c})
        return {"mask": mask.astype(bool), "score": score, "out_of_domain": ood}
