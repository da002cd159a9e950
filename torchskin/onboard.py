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
import threading

import numpy as np

from .errors import Parser, check_input_file, check_output_file, one_line


class _Model:
    KIND = "torchskin"
    IO: tuple[set, set] = (set(), set())

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
        names = ({i.name for i in self.session.get_inputs()}, {o.name for o in self.session.get_outputs()})
        if names != self.IO:
            want = f"inputs {sorted(self.IO[0])} and outputs {sorted(self.IO[1])}"
            raise ValueError(f"{self.path!r} is not a {self.KIND} model: it has inputs {sorted(names[0])} and outputs "
                             f"{sorted(names[1])}, expected {want}")
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
        if np.issubdtype(c.dtype, np.integer):
            c = c.astype(np.float64)  # whole degrees are fine
        if not np.issubdtype(c.dtype, np.floating):
            raise ValueError(f"config must hold numbers (degrees, metres), got {c.dtype}")
        with np.errstate(over="ignore"):
            c = c.astype(np.float32)
        if not np.isfinite(c).all():
            raise ValueError("config holds NaN, infinite or out-of-float32-range values")
        ood = ((c < self.domain[:, 0]) | (c > self.domain[:, 1])).any(1) if len(self.domain) else np.zeros(len(c), bool)
        return c, ood


def model_inputs(path) -> list[str]:
    """The input names of an ONNX model (``cube`` marks a detector, ``config`` alone a boundary model)."""
    import onnxruntime as ort

    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(f"cannot load ONNX model {str(path)!r}: {e}") from None
    return [i.name for i in sess.get_inputs()]


class Boundaries(_Model):
    """``boundaries.onnx``: configuration (N, k) -> boxes (N, 5) (b1, b2, c1, c2, d1; see ``box_order`` in the
    metadata; models exported before the NDVN rule give (N, 4))."""

    KIND = "boundaries (configuration -> boxes)"
    IO = ({"config"}, {"boxes"})

    def __call__(self, config) -> dict:
        c, ood = self._config(config)
        (boxes,) = self.session.run(None, {"config": c})
        return {"boxes": boxes, "out_of_domain": ood}


class Detector(_Model):
    """``detector.onnx``: reflectance cube (B, 4, H, W) + configuration (B, k) -> mask and score.

    Large frames are cut into tiles of ``tile`` pixels (each band's run of the flattened frame) that
    ``threads`` workers (the calling thread and a pool; one onnxruntime session, one intra-op thread each)
    pull from a shared queue, outputs bound straight into the result arrays, so the intermediates stay in
    cache: the frame is read from memory about once. A Detector keeps its tile buffers and pool between
    calls: create it once, and use one per calling thread (calls on one object must not overlap)."""

    KIND = "detector (cube + configuration -> mask, score)"
    IO = ({"cube", "config"}, {"mask", "score"})

    def __init__(self, path, threads: int | None = None, tile: int = 65536):
        super().__init__(path, threads)
        if tile < 1024:
            raise ValueError(f"tile must be >= 1024 pixels, got {tile}")
        self.tile = int(tile)
        self._buffers: dict[int, np.ndarray] = {}

    def _run_tiles(self, flat, c, mask, score, take, slot: int = 0, clipped=None, floor: float = 0.0) -> float:
        """Run the jobs (frame, first, last pixel) that ``take()`` hands out (None: done) with tile buffer
        ``slot``; return the smallest reflectance seen (NaN if any). ``clipped`` (per-frame counts): set
        negative values to 0 and count them. ``floor``: pixels whose band sum is not above it are not skin."""
        from onnxruntime import OrtValue

        io = self.session.io_binding()
        buf = self._buffers.get(slot)
        if buf is None:  # kept between calls: no fresh pages to fault in per frame
            buf = self._buffers[slot] = np.empty((1, 4, 1, self.tile), dtype=np.float32)
        io.bind_cpu_input("cube", buf)  # the tile buffer is bound once and refilled
        low, frame = np.inf, -1
        for b, lo, hi in iter(take, None):
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
            # outputs written in place (an OrtValue over the result arrays binds faster than bind_output)
            io.bind_ortvalue_output("mask", OrtValue.ortvalue_from_numpy(mask[b, lo:hi].reshape(1, 1, n)))
            io.bind_ortvalue_output("score", OrtValue.ortvalue_from_numpy(score[b, lo:hi].reshape(1, 1, n)))
            self.session.run_with_iobinding(io)
            if not np.isfinite(score[b, lo:hi].min()):  # +inf in a band gives a -inf (or NaN) score
                low = np.nan
            if floor > 0:
                mask[b, lo:hi] &= t[0, :, 0, :].sum(0) > floor
            if t is not buf:
                io.bind_cpu_input("cube", buf)
        return low

    def pixels(self, reflectance, config, chunk: int = 65536) -> dict:
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
    def _check_low(low) -> None:
        if np.isnan(low):
            raise ValueError("cube holds NaN or infinite reflectance")
        if low < 0:
            raise ValueError(f"cube holds negative reflectance (min {float(low):.3g}); noise on dark pixels? "
                             "negative='clip' (torchskin detect --clip-negative) sets it to 0")

    @property
    def default_min_reflectance(self) -> float:
        """The brightness floor the model was evaluated with (metadata ``min_reflectance``; 0 when absent)."""
        try:
            return float(self.meta.get("min_reflectance", 0.0))
        except ValueError:
            return 0.0

    def __call__(self, cube, config, out=None, negative: str = "error", min_reflectance: float | None = None) -> dict:
        """``out``: optional preallocated (mask, score) arrays, (B, H, W) bool and float32, C-contiguous, that
        receive the result (an onboard loop reuses them; their content is undefined if the call raises).
        ``negative``: "error" (default) raises on negative reflectance; "clip" sets it to 0 (the caller's
        cube is not modified) and reports the count per frame as ``clipped_values``. ``min_reflectance`` > 0:
        pixels whose mean reflectance over the bands is not above it are never skin (at the noise floor the
        indices are ratios of noise; e.g. 0.005 for ~3e-4 noise); 0 keeps the rules alone; None (default): the
        floor the model was evaluated with (``default_min_reflectance``, from its metadata)."""
        if negative not in ("error", "clip"):
            raise ValueError(f"negative must be 'error' or 'clip', got {negative!r}")
        if min_reflectance is None:
            min_reflectance = self.default_min_reflectance
        if not (0.0 <= float(min_reflectance) < 1.0):
            raise ValueError(f"min_reflectance must lie in [0, 1), got {min_reflectance}")
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
        floor = x.shape[1] * float(min_reflectance)  # on the band sum
        if B * n <= self.tile:  # small frames: one call
            if clipped is not None:
                clipped += np.count_nonzero(x < 0, axis=(1, 2, 3))
                x = np.maximum(x, 0)
            self._check_low(x.min())
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

        def take():  # workers pull the next tile: a worker that starts late simply takes fewer
            with lock:
                return next(queue, None)

        if k > 1 and self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="torchskin-detect")
        futures = [self._pool.submit(self._run_tiles, flat, c, mask, score, take, i, counts[i], floor)
                   for i in range(1, k)]
        lows = []
        try:  # the calling thread is worker 0
            lows.append(self._run_tiles(flat, c, mask, score, take, 0, counts[0], floor))
        finally:  # never return (or raise) while a worker still writes into the outputs
            lows += [f.result() for f in futures]
        low = np.min(lows)  # NaN propagates
        self._check_low(low)  # the outputs are discarded: no mask comes back from an invalid cube
        if clipped is not None:
            clipped += np.sum(counts, axis=0)
        if out is not None:
            return {"mask": out[0], "score": out[1], "out_of_domain": ood, **extra}
        return {"mask": mask.reshape(B, H, W), "score": score.reshape(B, H, W), "out_of_domain": ood, **extra}


# ------------------------------------------------------------------------- ELM for camera frames (numpy only)
def parse_roi(text: str) -> tuple[int, int, int, int]:
    """``"Y0:Y1:X0:X1"`` (rows Y0..Y1-1, columns X0..X1-1) -> a tuple of ints."""
    parts = str(text).split(":")
    try:
        roi = tuple(int(p) for p in parts)
    except ValueError:
        roi = ()
    if len(roi) != 4:
        raise ValueError(f"a panel region must be Y0:Y1:X0:X1 (integers), got {text!r}")
    return roi


def panel_signal(frame, roi, erode: int = 1) -> np.ndarray:
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


def elm_fit(frame, panels, erode: int = 1) -> dict:
    """Empirical line L = gain·ρ + offset per band (eqs 2.5.5-2.5.6) from reference panels in ``frame``
    (bands, H, W): ``panels`` is a sequence of (roi, reflectance), the reflectance a scalar or one value per
    band in (0, 1]. Two panels give the exact line through them; more give the least-squares line, whose RMS
    residual (reflectance units) is reported per band."""
    f = np.asarray(frame)
    if f.ndim != 3:
        raise ValueError(f"frame must be (bands, H, W), got shape {f.shape}")
    if len(panels) < 2:
        raise ValueError(f"ELM needs at least 2 reference panels, got {len(panels)}")
    nb = f.shape[0]
    refs, sig = [], []
    for roi, rho in panels:
        r = np.broadcast_to(np.asarray(rho, dtype=np.float64), (nb,)) if np.ndim(rho) == 0 else np.asarray(rho, np.float64)
        if r.shape != (nb,):
            raise ValueError(f"panel reflectance must be one value or {nb} (one per band), got {np.shape(rho)}")
        if not (np.all(r > 0) and np.all(r <= 1)):
            raise ValueError(f"panel reflectance must lie in (0, 1], got {r.tolist()}")
        refs.append(r)
        sig.append(panel_signal(f, roi, erode))
    R, L = np.stack(refs), np.stack(sig)  # (P, bands)
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


def elm_apply(cube, gain, offset) -> np.ndarray:
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


def cli_calibrate(argv: list[str]) -> int:
    """``torchskin calibrate --cube DN.npy (--panel Y0:Y1:X0:X1=REFL ... | --coefficients ELM.json) --out
    REFL.npy [--save-coefficients ELM.json] [--erode PX] [--json]`` (numpy only)."""

    from .io import save_npy, write_text

    ap = Parser(prog="torchskin calibrate", description="Signals (DN or radiance) to reflectance "
                                 "with the empirical line through reference panels in the frame (numpy only).")
    ap.add_argument("--cube", required=True, help=".npy signal cube (bands, H, W), or (B, bands, H, W) with "
                    "--coefficients")
    ap.add_argument("--panel", action="append", default=[], metavar="Y0:Y1:X0:X1=REFL",
                    help="a reference panel: pixel region and reflectance (one value, or one per band separated by "
                         "commas); repeat for each panel (at least 2)")
    ap.add_argument("--coefficients", help="apply a saved gain/offset JSON instead of fitting panels")
    ap.add_argument("--erode", type=int, default=1, help="pixels dropped on every side of a panel region (default 1)")
    ap.add_argument("--out", required=True, help="reflectance cube .npy (float32)")
    ap.add_argument("--save-coefficients", help="write the fitted gain/offset JSON (for later frames)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if bool(args.panel) == bool(args.coefficients):
        raise ValueError("give either --panel (at least twice) or --coefficients")
    out = check_output_file(args.out, "--out", (".npy",))
    save_coef = check_output_file(args.save_coefficients, "--save-coefficients", (".json",)) \
        if args.save_coefficients else None
    cube = load_cube(args.cube, "--cube")
    if args.coefficients:
        coef_path = check_input_file(args.coefficients, "--coefficients", (".json",))
        try:
            doc = json.loads(coef_path.read_text())
            gain, offset = np.asarray(doc["gain"], np.float64), np.asarray(doc["offset"], np.float64)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"cannot read --coefficients {args.coefficients!r}: {one_line(e)}") from None
        fit = None
    else:
        panels = []  # (region, reflectance)
        for p in args.panel:
            roi, sep, rho = p.partition("=")
            try:
                vals = [float(v) for v in rho.split(",")] if sep else []
            except ValueError:
                vals = []
            if not vals or not all(np.isfinite(vals)):
                raise ValueError(f"--panel must be Y0:Y1:X0:X1=REFL[,REFL...] with finite reflectances, got {p!r}")
            panels.append((parse_roi(roi), vals[0] if len(vals) == 1 else vals))
        if cube.ndim != 3:
            raise ValueError(f"fitting panels needs one frame (bands, H, W), got shape {cube.shape}")
        fit = elm_fit(cube, panels, args.erode)
        gain, offset = fit["gain"], fit["offset"]
    refl = elm_apply(cube, gain, offset)
    if not np.isfinite(refl).all():
        raise ValueError("the calibrated cube holds NaN or infinite values (check the coefficients)")
    coef = {"gain": gain.tolist(), "offset": offset.tolist()}
    if fit is not None:
        coef["panels"] = [{"region": list(roi), "reflectance": r.tolist(), "signal": s.tolist()}
                          for (roi, _), r, s in zip(panels, fit["references"], fit["signals"])]
        coef["residual"] = fit["residual"].tolist()
    coef_text = json.dumps(coef, indent=1)  # everything prepared before the first file is written
    save_npy(out, refl)
    if save_coef is not None:
        write_text(save_coef, coef_text)
    res = {**coef, "out": args.out, "shape": list(refl.shape),
           "reflectance_range": [float(refl.min()), float(refl.max())]}
    if args.json:
        print(json.dumps(res))
    else:
        print(f"wrote {args.out} {tuple(refl.shape)}: reflectance {res['reflectance_range'][0]:.4f} .. "
              f"{res['reflectance_range'][1]:.4f}; gain " + ", ".join(f"{v:.5g}" for v in gain)
              + "; offset " + ", ".join(f"{v:.5g}" for v in offset))
    return 0


def load_cube(path, option: str = "--cube") -> np.ndarray:
    """A numeric, non-empty, finite array from a ``.npy`` file (no pickles, no ``.npz`` archives), with a
    one-line ``ValueError`` naming ``option`` and the file otherwise."""
    p = check_input_file(path, option, (".npy",))
    try:
        x = np.load(p, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"cannot read {option} {str(p)!r}: {one_line(e)}") from None
    if not isinstance(x, np.ndarray):
        raise ValueError(f"{option} {str(p)!r} is not a single .npy array")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise ValueError(f"{option} {str(p)!r} must hold numbers, got dtype {x.dtype}")
    if x.size == 0:
        raise ValueError(f"{option} {str(p)!r} is empty (shape {x.shape})")
    if np.issubdtype(x.dtype, np.floating) and not np.isfinite(x).all():
        raise ValueError(f"{option} {str(p)!r} holds NaN or infinite values")
    return x


FLAG_FOR_FEATURE = {"sun_zenith_deg": "sun_zenith", "camera_zenith_deg": "camera_zenith",
                    "relative_azimuth_deg": "relative_azimuth", "range_m": "range"}


def write_png(path, mask: np.ndarray) -> None:
    """A greyscale PNG of a boolean (H, W) mask (stdlib zlib; no imaging library), written atomically."""
    import struct
    import zlib

    from .io import write_bytes

    m = (np.asarray(mask, dtype=bool).astype(np.uint8) * 255)
    h, w = m.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), m], 1).tobytes()  # filter byte 0 before every row

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    write_bytes(path, png)


def cli_detect(argv: list[str]) -> int:
    """``torchskin detect --model detector.onnx --cube CUBE.npy --sun-zenith DEG --camera-zenith DEG
    --relative-azimuth DEG [--range M] [--out MASK.png] [--json]`` (numpy + onnxruntime only)."""

    ap = Parser(prog="torchskin detect", description="Skin mask of a reflectance cube with the "
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
    ap.add_argument("--min-reflectance", type=float, default=None,
                    help="pixels whose mean reflectance over the bands is not above this are never skin (their "
                         "indices are noise); default: the floor the model was evaluated with (its metadata "
                         "min_reflectance; 0 for models without it)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    mask_path = check_output_file(args.out, "--out", (".png",)) if args.out else None
    det = Detector(check_input_file(args.model, "--model", (".onnx",)))
    cube = load_cube(args.cube, "--cube")
    if cube.ndim == 3:
        cube = cube[None]
    values = []
    for f in det.features:
        flag = FLAG_FOR_FEATURE.get(f, f)
        v = getattr(args, flag, None)
        if v is None:
            raise ValueError(f"the model needs --{flag.replace('_', '-')} ({f})")
        if not np.isfinite(v):
            raise ValueError(f"--{flag.replace('_', '-')} must be a finite number, got {v}")
        values.append(v)
    out = det(cube, np.tile(np.array(values, dtype=np.float64), (cube.shape[0], 1)),
              negative="clip" if args.clip_negative else "error", min_reflectance=args.min_reflectance)
    if mask_path is not None:
        write_png(mask_path, out["mask"][0])
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
