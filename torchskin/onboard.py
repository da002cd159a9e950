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
        lo = x.min()  # one pass: NaN propagates through min
        if np.isnan(lo):
            raise ValueError("cube holds NaN reflectance")
        if lo < 0:
            raise ValueError("cube holds negative reflectance")
        c, ood = self._config(config)
        if c.shape[0] != x.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for a batch of {x.shape[0]} frames")
        mask, score = self.session.run(None, {"cube": np.ascontiguousarray(x), "config": c})
        return {"mask": mask.astype(bool), "score": score, "out_of_domain": ood}


FLAG_FOR_FEATURE = {"sun_zenith_deg": "sun_zenith", "camera_zenith_deg": "camera_zenith",
                    "relative_azimuth_deg": "relative_azimuth", "range_m": "range"}


def write_png(path, mask: np.ndarray) -> None:
    """A greyscale PNG of a boolean (H, W) mask (stdlib zlib; no imaging library), written atomically."""
    import os
    import struct
    import tempfile
    import zlib

    m = (np.asarray(mask, dtype=bool).astype(np.uint8) * 255)
    h, w = m.shape
    raw = b"".join(b"\x00" + m[i].tobytes() for i in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".mask.", suffix=".png", dir=d)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(png)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def cli_detect(argv: list[str]) -> int:
    """``torchskin detect --model detector.onnx --cube CUBE.npy --sun-zenith DEG --camera-zenith DEG
    --relative-azimuth DEG [--range M] [--out MASK.png] [--json]`` (numpy + onnxruntime only)."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="torchskin detect", description="Skin mask of a reflectance cube with the "
                                 "exported detector (numpy + onnxruntime, no torch).")
    ap.add_argument("--model", required=True, help="detector.onnx")
    ap.add_argument("--cube", required=True, help=".npy reflectance cube (4, H, W) or (B, 4, H, W), float32")
    ap.add_argument("--sun-zenith", type=float, help="degrees")
    ap.add_argument("--camera-zenith", type=float, help="degrees")
    ap.add_argument("--relative-azimuth", type=float, help="degrees, |sun - camera azimuth| in [0, 180]")
    ap.add_argument("--range", type=float, help="metres (if the model uses it)")
    ap.add_argument("--out", help="mask PNG (first frame)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    try:
        det = Detector(args.model)
        try:
            cube = np.load(args.cube)
        except (OSError, ValueError) as e:
            raise ValueError(f"cannot read cube {args.cube!r}: {e}") from None
        if cube.ndim == 3:
            cube = cube[None]
        values = []
        for f in det.features:
            v = getattr(args, FLAG_FOR_FEATURE.get(f, f), None)
            if v is None:
                raise ValueError(f"the model needs --{FLAG_FOR_FEATURE.get(f, f).replace('_', '-')} ({f})")
            values.append(v)
        out = det(cube, np.tile(np.array(values, dtype=np.float64), (cube.shape[0], 1)))
        if args.out:
            write_png(args.out, out["mask"][0])
        frac = float(out["mask"].mean())
        if args.json:
            print(json.dumps({"skin_fraction": frac, "skin_pixels": int(out["mask"].sum()),
                              "out_of_domain": out["out_of_domain"].tolist(), "shape": list(out["mask"].shape)}))
        else:
            flag = " (configuration OUTSIDE the training domain)" if out["out_of_domain"].any() else ""
            print(f"skin pixels {int(out['mask'].sum())} of {out['mask'].size} ({frac:.4f}){flag}")
        return 0
    except ValueError as e:
        print(f"torchskin detect: error: {e}", file=sys.stderr)
        return 2
