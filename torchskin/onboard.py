"""Onboard runtime: load the exported ONNX models and run them with numpy and onnxruntime only (no torch).

    det = Detector("exports/detector.onnx")
    out = det(cube, config)      # cube (B, 4, H, W) float32 reflectance, config (B, k) in the model's units
    out["mask"], out["score"], out["out_of_domain"]

``score`` is the smallest margin to a box edge in index units weighted by the band-pair sum (positive inside;
see ``torchskin.export.Detector``).

Inputs are validated: wrong rank, band count or dtype, NaN or negative reflectance raise ``ValueError``;
configurations outside the training domain are flagged per frame in ``out_of_domain`` (never silently used).
Calibrated frames of dark pixels (sky, deep shadow) carry slightly negative reflectance from sensor noise:
``det(cube, config, negative="clip")`` sets those values to 0 instead and counts them per frame in
``clipped_values`` (a pixel whose band pairs sum to 0 is never skin).
"""

from __future__ import annotations

import json

import numpy as np


class _Model:
    def __init__(self, path, threads: int | None = None):
        import os

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
        meta = self.session.get_modelmeta().custom_metadata_map
        self.meta = dict(meta)
        self.features = json.loads(meta.get("features", "[]"))
        self.domain = np.array(json.loads(meta.get("feature_domain", "[]")), dtype=np.float64).reshape(-1, 2)
        self.bands_nm = json.loads(meta.get("bands_nm", "[]"))
        self._pool = None

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
    """``detector.onnx``: reflectance cube (B, 4, H, W) + configuration (B, k) -> mask and score.

    Large frames are cut into tiles of ``tile`` pixels (each band's run of the flattened frame) that run on
    ``threads`` workers (one onnxruntime session, one intra-op thread each, outputs bound straight into the
    result arrays), so the intermediates stay in cache: the frame is read from memory about once."""

    def __init__(self, path, threads: int | None = None, tile: int = 65536):
        super().__init__(path, threads)
        if tile < 1024:
            raise ValueError(f"tile must be >= 1024 pixels, got {tile}")
        self.tile = int(tile)
        self._buffers: dict[int, np.ndarray] = {}

    def _run_tiles(self, flat, c, mask, score, jobs, slot: int = 0, clipped=None) -> float:
        """Run ``jobs`` (frame, first, last pixel) with tile buffer ``slot``; return the smallest reflectance
        seen (NaN if any). ``clipped`` (per-frame counts): set negative values to 0 and count them."""
        io = self.session.io_binding()
        buf = self._buffers.get(slot)
        if buf is None:  # kept between calls: no fresh pages to fault in per frame
            buf = self._buffers[slot] = np.empty((1, 4, 1, self.tile), dtype=np.float32)
        io.bind_cpu_input("cube", buf)  # the tile buffer is bound once and refilled
        low, frame = np.inf, -1
        for b, lo, hi in jobs:
            n = hi - lo
            if n != self.tile:  # the ragged last tile of a frame
                t = np.empty((1, 4, 1, n), dtype=np.float32)
                io.bind_cpu_input("cube", t)
            else:
                t = buf
            t[0, :, 0, :] = flat[b, :, lo:hi]
            if clipped is not None:
                clipped[b] += np.count_nonzero(t < 0)
                np.maximum(t, 0, out=t)  # NaN stays NaN
            low = np.minimum(low, t.min())  # validation while the tile is in cache (NaN propagates)
            if b != frame:
                io.bind_cpu_input("config", c[b:b + 1])
                frame = b
            io.bind_output("mask", "cpu", 0, np.bool_, (1, 1, n), mask[b, lo:hi].ctypes.data)
            io.bind_output("score", "cpu", 0, np.float32, (1, 1, n), score[b, lo:hi].ctypes.data)
            self.session.run_with_iobinding(io)
            if t is not buf:
                io.bind_cpu_input("cube", buf)
        return low

    @staticmethod
    def _check_low(low) -> None:
        if np.isnan(low):
            raise ValueError("cube holds NaN reflectance")
        if low < 0:
            raise ValueError(f"cube holds negative reflectance (min {float(low):.3g}); noise on dark pixels? "
                             "negative='clip' (torchskin detect --clip-negative) sets it to 0")

    def __call__(self, cube, config, out=None, negative: str = "error") -> dict:
        """``out``: optional preallocated (mask, score) arrays, (B, H, W) bool and float32, C-contiguous, that
        receive the result (an onboard loop reuses them; their content is undefined if the call raises).
        ``negative``: "error" (default) raises on negative reflectance; "clip" sets it to 0 (the caller's
        cube is not modified) and reports the count per frame as ``clipped_values``."""
        if negative not in ("error", "clip"):
            raise ValueError(f"negative must be 'error' or 'clip', got {negative!r}")
        x = np.asarray(cube)
        if x.ndim != 4:
            raise ValueError(f"cube must have rank 4 (B, bands, H, W), got shape {x.shape}")
        if x.shape[1] != len(self.bands_nm or [0] * 4):
            raise ValueError(f"cube must have {len(self.bands_nm)} bands ({self.bands_nm} nm) on axis 1, "
                             f"got {x.shape[1]}")
        if x.dtype != np.float32:
            raise ValueError(f"cube must be float32 reflectance, got {x.dtype}")
        if x.size == 0:
            raise ValueError(f"cube is empty: shape {x.shape}")
        c, ood = self._config(config)
        if c.shape[0] != x.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for a batch of {x.shape[0]} frames")
        B, _, H, W = x.shape
        n = H * W
        if out is not None:
            if (not isinstance(out, (tuple, list)) or len(out) != 2
                    or not all(isinstance(a, np.ndarray) for a in out)):
                raise ValueError("out must be a (mask, score) pair of numpy arrays")
            for a, dt, name in ((out[0], np.bool_, "mask"), (out[1], np.float32, "score")):
                if a.shape != (B, H, W) or a.dtype != dt or not a.flags.c_contiguous or not a.flags.writeable:
                    raise ValueError(f"out {name} must be a writeable C-contiguous {np.dtype(dt).name} array of shape "
                                     f"{(B, H, W)}, got {a.dtype} {a.shape}")
        clipped = np.zeros(B, dtype=np.int64) if negative == "clip" else None
        extra = {} if clipped is None else {"clipped_values": clipped}
        if B * n <= self.tile:  # small frames: one call
            if clipped is not None:
                clipped += np.count_nonzero(x < 0, axis=(1, 2, 3))
                x = np.maximum(x, 0)
            self._check_low(x.min())
            mask, score = self.session.run(None, {"cube": np.ascontiguousarray(x), "config": c})
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
        counts = None if clipped is None else [np.zeros(B, dtype=np.int64) for _ in range(k)]  # one per worker
        if k == 1:
            low = self._run_tiles(flat, c, mask, score, jobs, 0, None if counts is None else counts[0])
        else:
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="torchskin-detect")
            futures = [self._pool.submit(self._run_tiles, flat, c, mask, score, jobs[i::k], i,
                                         None if counts is None else counts[i]) for i in range(k)]
            low = np.min([f.result() for f in futures])  # NaN propagates
        self._check_low(low)  # the outputs are discarded: no mask comes back from an invalid cube
        if counts is not None:
            clipped += np.sum(counts, axis=0)
        if out is not None:
            return {"mask": out[0], "score": out[1], "out_of_domain": ood, **extra}
        return {"mask": mask.reshape(B, H, W), "score": score.reshape(B, H, W), "out_of_domain": ood, **extra}


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
    ap.add_argument("--clip-negative", action="store_true",
                    help="set negative reflectance (noise on dark pixels) to 0 and report how many values were "
                         "clipped, instead of refusing the cube")
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
        out = det(cube, np.tile(np.array(values, dtype=np.float64), (cube.shape[0], 1)),
                  negative="clip" if args.clip_negative else "error")
        if args.out:
            write_png(args.out, out["mask"][0])
        frac = float(out["mask"].mean())
        clipped = out.get("clipped_values")
        if args.json:
            res = {"skin_fraction": frac, "skin_pixels": int(out["mask"].sum()),
                   "out_of_domain": out["out_of_domain"].tolist(), "shape": list(out["mask"].shape)}
            if clipped is not None:
                res["clipped_values"] = clipped.tolist()
            print(json.dumps(res))
        else:
            flag = " (configuration OUTSIDE the training domain)" if out["out_of_domain"].any() else ""
            clip = f"; {int(clipped.sum())} negative values clipped to 0" if clipped is not None else ""
            print(f"skin pixels {int(out['mask'].sum())} of {out['mask'].size} ({frac:.4f}){flag}{clip}")
        return 0
    except ValueError as e:
        print(f"torchskin detect: error: {e}", file=sys.stderr)
        return 2
