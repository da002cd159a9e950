"""The onboard models run by onnxruntime: ``OnboardDetector`` (``detector.onnx``: cube + configuration -> mask,
score), its tiles, workers and input checks, and ``OnboardBoxes`` (configuration -> boxes). numpy and onnxruntime
only (no torch)."""

from __future__ import annotations

import functools
import json
import os
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, cast

import numpy as np
from numpy.typing import ArrayLike

from ..bands import BandSet
from ..io import as_float32
from .checks import _MAX_BITS, REFLECTANCE_MAX, check_reflectance_range
from .heads import FLOOR_BAND, detector_head

if TYPE_CHECKING:
    from concurrent.futures import ThreadPoolExecutor

    import onnxruntime as ort

    from .lut import LutHead

#: the shipped detector, packaged with torchskin (a copy of the repository's ``exports/detector.onnx``, made by
#: ``make demo``'s export step): ``torchskin detect``'s and ``OnboardDetector``'s default model
#: (``torchskin/data/detector.onnx``: this module lies in ``torchskin/onboard/``)
SHIPPED_DETECTOR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data",
                                "detector.onnx")


def _session(path: str) -> ort.InferenceSession:
    """The onnxruntime session of the graph at ``path``: one intra- and inter-op thread (frames are split into tiles
    that run on the detector's workers instead). Detectors of one unchanged file share a session (onnxruntime's
    ``run`` is thread-safe; each worker binds its own buffers): loading a 38 MB lookup table costs ~0.06 s."""
    import onnxruntime  # noqa: F401  (a missing package is named as such: errors.EXTRAS, not a model error)

    try:
        st = os.stat(path)
        return _cached_session(os.path.abspath(path), st.st_mtime_ns, st.st_size)
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(f"cannot load ONNX model {path!r}: {e}") from None


@functools.lru_cache(maxsize=8)
def _cached_session(path: str, mtime_ns: int, size: int) -> ort.InferenceSession:
    """``_session`` of one version of a file (its absolute path, modification time and size)."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


class _Model:
    KIND = "torchskin"
    IO: tuple[set, set] = (set(), set())

    def __init__(self, path: str | os.PathLike, threads: int | None = None):

        self.path = str(path)
        self.threads = max(1, int(threads or min(os.cpu_count() or 1, 8)))
        self.session = _session(self.path)
        names = ({i.name for i in self.session.get_inputs()}, {o.name for o in self.session.get_outputs()})
        if names != self.IO:
            want = f"inputs {sorted(self.IO[0])} and outputs {sorted(self.IO[1])}"
            raise ValueError(f"{self.path!r} is not a {self.KIND} model: it has inputs {sorted(names[0])} and outputs "
                             f"{sorted(names[1])}, expected {want}")
        meta = self.session.get_modelmeta().custom_metadata_map
        self.meta = dict(meta)
        self.features = json.loads(meta.get("features", "[]"))
        self.domain = np.array(json.loads(meta.get("feature_domain", "[]")), dtype=np.float64).reshape(-1, 2)
        #: the detector kind the graph records (metadata ``kind``: ``boxes``, ``classifier``, ...); None for exports
        #: made before graphs recorded it
        self.kind: str | None = meta.get("kind")
        #: the model's bands (metadata ``bands``, centres and FWHM); None for exports made before graphs recorded
        #: them (``bands_nm``, centres alone, and ``fwhm_nm`` then)
        self.band_set: BandSet | None = None
        if "bands" in meta:
            try:
                self.band_set = BandSet.from_json(meta["bands"])
            except ValueError as e:
                raise ValueError(f"cannot load ONNX model {self.path!r}: its metadata 'bands' is not a band set: {e}") \
                    from None
        self.bands_nm = list(self.band_set.centers) if self.band_set is not None \
            else json.loads(meta.get("bands_nm", "[]"))
        #: how many bands a cube holds for this model (its ``bands_nm``; four for exports that name none)
        self.n_bands = len(self.bands_nm) or 4
        self._pool: ThreadPoolExecutor | None = None

    def config_row(self, **values: float) -> list[float]:
        """One frame's configuration in this model's feature order (``features``) from values by feature name;
        ``ValueError`` naming a feature the model takes that is not given (names it does not take are ignored).

        >>> # det.config_row(sun_zenith_deg=45, camera_zenith_deg=90, relative_azimuth_deg=20, diffuse_share=0.17)
        """
        missing = [f for f in self.features if f not in values]
        if missing:
            raise ValueError(f"the model takes {', '.join(missing)} as well (its features: {', '.join(self.features)})")
        return [float(values[f]) for f in self.features]

    def _config(self, config: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
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
        ood = cast(np.ndarray, ((c < self.domain[:, 0]) | (c > self.domain[:, 1])).any(1)) if len(self.domain) \
            else np.zeros(len(c), bool)
        return c, ood


def model_inputs(path: str | os.PathLike) -> list[str]:
    """The input names of an ONNX model (``cube`` marks a detector, ``config`` alone a box model: ``OnboardBoxes``)."""
    import onnxruntime as ort

    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(f"cannot load ONNX model {str(path)!r}: {e}") from None
    return [i.name for i in sess.get_inputs()]


class _TileBinding:
    """One worker's buffers for tiles of ``n`` pixels and the onnxruntime bindings over them, made once and kept
    by the detector between calls (binding costs ~0.1 ms a worker and a call otherwise): the (4, n) tile, the
    (E, n) edge rows and (n,) band sum of a split box graph (``_EdgeHead``), its weight buffers, the floor's (n,)
    bool scratch; ``frame``: the frame whose weights (or configuration) are bound, -1 at the start of a call."""

    def __init__(self, det: OnboardDetector, n: int):
        self.head = det._split[1] if det._split is not None else None
        rows = self.head.e if self.head is not None else 0
        self.t, self.edges = np.empty((det.n_bands, n), dtype=np.float32), np.empty((rows, n), dtype=np.float32)
        self.total, self.dark = np.empty(n, dtype=np.float32), np.empty(n, dtype=bool)
        self.bits = self.t.view(np.uint32)  # the tile's values as unsigned integers (``_MAX_BITS``)
        self.nir_min = np.zeros((), dtype=np.float32)  # the head's minimum of the tile's FLOOR_BAND
        self.frame, self.ws = -1, []
        self.lut = det._lut.scratch(n) if det._lut is not None else None  # the lookup-table head's buffers
        self.table: np.ndarray | None = None  # the frame's table slice (lookup-table head)
        if self.head is not None:
            self.io, self.sums = self.head.session.io_binding(), self.head.sums.io_binding()
            self.head.bind(self.io, self.sums, self.t, self.edges, self.total, self.nir_min)
            self.ws = self.head.bind_weights(self.io)
        else:  # a plain (bands, n) array, bound as (1, bands, 1, n): numpy fills it faster than a 4-d view
            self.io, self.sums = det.session.io_binding(), None
            self.io.bind_cpu_input("cube", self.t.reshape(1, det.n_bands, 1, n))

    def band_sum(self) -> None:
        """The band sum of the tile into ``total`` (the head's ``sums`` session)."""
        self.head.sums.run_with_iobinding(self.sums)  # type: ignore[union-attr]


class OnboardBoxes(_Model):
    """The boxes of a ``boxes``-kind model, exported as ``boundaries.onnx`` (or ``baseline_box.onnx``) and run by
    onnxruntime: configuration (N, k) -> boxes (N, 5) (b1, b2, c1, c2, d1; see ``box_order`` in the metadata; models
    exported before the NDVN rule give (N, 4))."""

    KIND = "boundaries (configuration -> boxes)"
    IO = ({"config"}, {"boxes"})

    def __call__(self, config: ArrayLike) -> dict:
        """``{"boxes": (N, 5) float32, "out_of_domain": (N,) bool}`` of configurations (N, k) or (k,)."""
        c, ood = self._config(config)
        (boxes,) = self.session.run(None, {"config": c})
        return {"boxes": boxes, "out_of_domain": ood}


class OnboardDetector(_Model):
    """``detector.onnx`` run by onnxruntime: reflectance cube (B, 4, H, W) + configuration (B, k) -> mask and
    score (the torch reference: ``torchskin.detectors.boxes.BoxDetector`` or
    ``torchskin.detectors.classifier.ClassifierDetector``).

    Large frames are cut into tiles of ``tile`` pixels (each band's run of the flattened frame) that
    ``threads`` workers (the calling thread and a pool; one onnxruntime session, one intra-op thread each)
    pull from a shared queue, outputs bound straight into the result arrays, so the intermediates stay in
    cache: the frame is read from memory about once. An OnboardDetector keeps its tile buffers and pool between
    calls: create it once, and use one per calling thread (calls on one object must not overlap).

    The head the tiles run on (``head_name``) follows the graph's metadata ``kind`` (``detector_head``): a box
    kind's graph computes its edge matrices once per frame and runs a rebuilt per-pixel head ("boxes"); any other
    kind's graph runs as it is ("generic"). Graphs exported before they recorded ``kind`` are told by their node
    names. The model's bands come from the metadata ``bands`` (``band_set``, centres and FWHM), else ``bands_nm``."""

    KIND = "detector (cube + configuration -> mask, score)"
    IO = ({"cube", "config"}, {"mask", "score"})

    def __init__(self, path: str | os.PathLike = SHIPPED_DETECTOR, threads: int | None = None, tile: int = 65536):
        super().__init__(path, threads)
        if tile < 1024:
            raise ValueError(f"tile must be >= 1024 pixels, got {tile}")
        self.tile = int(tile)
        self._bindings: dict[int, dict[int, _TileBinding]] = {}  # per worker, per tile size (``_TileBinding``)
        #: the head the graph runs on, by its metadata ``kind`` (``detector_head``): "boxes" or "generic"
        self.head_name, head = detector_head(self.meta, self.path, self.session.get_session_options())
        #: the box head's (per-frame session, tile head), or None
        self._split: tuple | None = head if self.head_name == "boxes" else None
        #: the lookup-table head (``onboard.lut.LutHead``), or None
        self._lut: LutHead | None = head if self.head_name == "lut" else None

    @staticmethod
    def _check_tile(t: np.ndarray, b: int, clipped: np.ndarray | None) -> tuple[float, float, int]:
        """Validate a (4, n) tile while it is in cache: its smallest and largest value and how many exceed
        ``REFLECTANCE_MAX`` (NaN propagates), clipping negative values to 0 (counted in ``clipped[b]``) when
        ``clipped`` is given. Only for a tile that failed the one-pass test of ``_run_tiles`` (its values' integer
        maximum at most ``_MAX_BITS``: every value within [0, ``REFLECTANCE_MAX``], the usual calibrated tile); the
        largest value goes to ``check_reflectance_range`` (``REFLECTANCE_CEILING``) with the frame's."""
        low, top = t.min(), t.max()
        over = int(np.count_nonzero(t > REFLECTANCE_MAX)) if top > REFLECTANCE_MAX else 0
        if clipped is not None:
            clipped[b] += np.count_nonzero(t < 0)
            np.maximum(t, 0, out=t)  # NaN stays NaN
        return low, top, over

    @staticmethod
    def _apply_floor(t: np.ndarray, m: np.ndarray, floor: float, total: np.ndarray,
                     band_sum: Callable[[], None] | None = None, dark: np.ndarray | None = None) -> None:
        """``m &= t.sum(0) > floor`` (the band sum in band order, as float32) for a non-negative (4, n) tile ``t``
        and its mask ``m`` (``__call__`` refuses or clips negative values before the floor). A masked pixel whose
        third band (1080 nm: bright for skin, vegetation and most materials) lies above the floor keeps its mask
        without a sum: its sum is at least that band (the others are non-negative, and float32 addition of
        non-negative terms never rounds below either), so only the masked pixels dark in that band (``dark``, an
        (n,) bool scratch buffer) are summed: nothing more where no pixel is dark in it (most tiles: one comparison
        over a quarter of the tile), at those pixels alone when they are few (the same sums), and over the tile
        into ``total`` otherwise (by ``band_sum()`` when given: the head's ``sums`` session)."""
        dark = np.empty(len(m), dtype=bool) if dark is None else dark
        np.less_equal(t[min(FLOOR_BAND, len(t) - 1)], floor, out=dark)
        if not dark.any():  # no pixel dark in that band (most tiles): two passes over in-cache rows
            return
        np.logical_and(dark, m, out=dark)
        count = np.count_nonzero(dark)
        if not count:
            return
        if 16 * count < len(m):
            idx = np.flatnonzero(dark)
            s = t[0, idx]
            for k in range(1, t.shape[0]):
                s += t[k, idx]
            m[idx[~(s > floor)]] = False
            return
        if band_sum is not None:
            band_sum()
        else:
            np.add(t[0], t[1], out=total)
            for k in range(2, t.shape[0]):
                np.add(total, t[k], out=total)
        np.logical_and(m, total > floor, out=m)

    def _run_tiles(self, flat: np.ndarray, c: np.ndarray, mask: np.ndarray, score: np.ndarray,
                   take: Callable[[], tuple[int, int, int] | None], slot: int = 0, clipped: np.ndarray | None = None,
                   floor: float = 0.0, frame_weights: Callable[[int], list[np.ndarray]] | None = None,
                   ) -> tuple[float, float, int]:
        """Run the jobs (frame, first, last pixel) that ``take()`` hands out (None: done) with tile buffers
        ``slot``; return the smallest and largest reflectance seen before clipping (NaN if any) and how many values
        exceed ``REFLECTANCE_MAX`` (``_check_tile``; (0, 0, 0) when all lie within [0, ``REFLECTANCE_MAX``]).
        ``clipped`` (per-frame counts): set negative values to 0 and count them. ``floor``: pixels whose band sum
        is not above it are not skin.
        A box graph runs split (``_split_box_graph``): its edge matrices once per frame, its per-pixel head
        (``_EdgeHead``) per tile; other graphs run whole per tile."""
        from onnxruntime import OrtValue

        head = self._split[1] if self._split is not None else None
        lut = self._lut
        low, high, over = 0.0, 0.0, 0
        run = head.session.run_with_iobinding if head is not None else self.session.run_with_iobinding
        minimum, greater = np.minimum.reduce, np.greater
        bindings = self._bindings.setdefault(slot, {})  # this worker's alone
        for tb in bindings.values():
            tb.frame = -1  # nothing of this call bound yet
        for b, lo, hi in iter(take, None):
            n = hi - lo
            tb = bindings.get(n) or self._binding(bindings, n)
            t, edges = tb.t, tb.edges
            if lut is not None and int((view := flat[b, :, lo:hi]).view(np.uint32).max()) <= _MAX_BITS:
                t, checked = view, None  # the lookup-table head reads the frame's rows in place
            else:
                t[...] = flat[b, :, lo:hi]
                # the usual tile's one pass: every value within range (``_MAX_BITS``), else the full check
                checked = None if int(tb.bits.max()) <= _MAX_BITS else self._check_tile(t, b, clipped)
            if checked is not None:
                low, high, over = np.minimum(low, checked[0]), np.maximum(high, checked[1]), over + checked[2]
            if b != tb.frame:  # a frame's edge matrices from its configuration alone (batch 1, as the whole graph)
                if lut is not None:  # a lookup table: the frame's slice
                    sl = lut.slice_of(c[b])
                    tb.table = lut.table(sl)
                elif head is not None:  # copied into the bound weight buffers
                    for w, v in zip(tb.ws, frame_weights(b), strict=True):  # type: ignore[misc]
                        w[...] = v
                else:
                    tb.io.bind_cpu_input("config", c[b:b + 1])
                tb.frame = b
            m, sc = mask[b, lo:hi], score[b, lo:hi]
            if lut is not None:
                lut.run(t, cast(np.ndarray, tb.table), m, sc, cast(dict, tb.lut))
            elif head is not None:
                run(tb.io)
                minimum(edges, axis=0, out=sc)  # the graph's Min
                greater(sc, 0, out=m)  # and its Greater
            else:  # outputs written in place (an OrtValue over the result arrays binds faster than bind_output)
                tb.io.bind_ortvalue_output("mask", OrtValue.ortvalue_from_numpy(m.reshape(1, 1, n)))
                tb.io.bind_ortvalue_output("score", OrtValue.ortvalue_from_numpy(sc.reshape(1, 1, n)))
                run(tb.io)
            if checked is not None and not np.isfinite(sc.min()):  # +inf in a band gives a -inf (or NaN) score
                low = np.nan
            if floor > 0 and not (head is not None and tb.nir_min > floor):  # (one band above the floor: so is
                self._apply_floor(t, m, floor, tb.total, tb.band_sum if head is not None else None, tb.dark)  # the sum)
        return low, high, over

    def _binding(self, bindings: dict[int, _TileBinding], n: int) -> _TileBinding:
        """A worker's buffers and bindings for tiles of ``n`` pixels, made on first use and kept in its
        ``bindings``: the full tile's and one ragged size's (a frame's last tile; another size replaces it)."""
        if n != self.tile:
            for k in [k for k in bindings if k != self.tile]:
                del bindings[k]
        tb = bindings[n] = _TileBinding(self, n)
        return tb

    def pixels(self, reflectance: ArrayLike, config: ArrayLike, chunk: int = 65536) -> dict:
        """The detector graph on separate pixels, each with its own configuration: ``reflectance`` (n, bands) and
        ``config`` (n, k) run as a (n, bands, 1, 1) cube in chunks of ``chunk`` pixels (negative values clipped to 0,
        as ``negative="clip"``; no brightness floor). Returns ``mask`` (n,) bool and ``score`` (n,) float32."""
        r = np.asarray(reflectance, dtype=np.float32)
        if r.ndim != 2 or r.shape[1] != self.n_bands:
            raise ValueError(f"reflectance must be (n, {self.n_bands}), got shape {r.shape}")
        if not np.isfinite(r).all():
            raise ValueError("reflectance holds NaN or infinite values")
        c, _ = self._config(config)
        if c.shape[0] != r.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for {r.shape[0]} pixels")
        mask, score = np.empty(len(r), dtype=bool), np.empty(len(r), dtype=np.float32)
        for lo in range(0, len(r), chunk):
            hi = min(lo + chunk, len(r))
            cube = np.maximum(r[lo:hi], 0).reshape(hi - lo, self.n_bands, 1, 1)
            m, sc = self.session.run(None, {"cube": cube, "config": c[lo:hi]})
            mask[lo:hi], score[lo:hi] = m.reshape(-1), sc.reshape(-1)
        return {"mask": mask, "score": score}

    @staticmethod
    def _check_low(low: float, high: float = 0.0, clip: bool = False, above: float | None = 1.0) -> None:
        """``ValueError`` for a cube whose smallest and largest values (before clipping) are ``low`` and
        ``high``, with a share ``above`` of its values above ``REFLECTANCE_MAX``: NaN, out of meaning
        (``check_reflectance_range``), or negative unless ``clip``. ``above`` None: the upper bounds (the share
        and ``REFLECTANCE_CEILING``) are the caller's (``range_check=False``)."""
        if not (np.isfinite(low) and np.isfinite(high)):
            raise ValueError("cube holds NaN or infinite reflectance")
        check_reflectance_range(low, 0.0 if above is None else high, 0.0 if above is None else above)
        if low < 0 and not clip:
            raise ValueError(f"cube holds negative reflectance (min {float(low):.3g}); noise on dark pixels? "
                             "negative='clip' (torchskin detect --clip-negative) sets it to 0")

    def _check_cube(self, cube: ArrayLike) -> np.ndarray:
        """``cube`` as an array, after the checks of rank, band count, dtype and size (``ValueError``)."""
        x = np.asarray(cube)
        if x.ndim != 4:
            raise ValueError(f"cube must have rank 4 (B, bands, H, W), got shape {x.shape}")
        if x.shape[1] != self.n_bands:
            raise ValueError(f"cube must have {len(self.bands_nm)} bands ({self.bands_nm} nm) on axis 1, "
                             f"got {x.shape[1]}")
        if x.size == 0:
            raise ValueError(f"cube is empty: shape {x.shape}")
        try:
            return as_float32(x)  # float64, float16, either byte order, integers: converted alike
        except ValueError as e:
            raise ValueError(f"cube {e}") from None

    @staticmethod
    def _check_out(out: tuple[np.ndarray, np.ndarray], shape: tuple[int, int, int]) -> None:
        """``ValueError`` unless ``out`` is a (mask, score) pair of writeable C-contiguous bool and float32 arrays
        of ``shape``."""
        if (not isinstance(out, (tuple, list)) or len(out) != 2
                or not all(isinstance(a, np.ndarray) for a in out)):
            raise ValueError("out must be a (mask, score) pair of numpy arrays")
        for a, dt, name in ((out[0], np.bool_, "mask"), (out[1], np.float32, "score")):
            if a.shape != shape or a.dtype != dt or not a.flags.c_contiguous or not a.flags.writeable:
                raise ValueError(f"out {name} must be a writeable C-contiguous {np.dtype(dt).name} array of shape "
                                 f"{shape}, got {a.dtype} {a.shape}")

    @property
    def default_min_reflectance(self) -> float:
        """The brightness floor the model was evaluated with (metadata ``min_reflectance``; 0 when absent)."""
        try:
            return float(self.meta.get("min_reflectance", 0.0))
        except ValueError:
            return 0.0

    def __call__(self, cube: np.ndarray, config: ArrayLike, out: tuple[np.ndarray, np.ndarray] | None = None,
                 negative: str = "error", min_reflectance: float | None = None, range_check: bool = True) -> dict:
        """Detect skin in ELM reflectance frames.

        Args:
            cube: reflectance (float32; other float and integer dtypes are converted), bands (544, 633, 1080,
                1580 nm: the model's ``bands_nm``) on axis 1; finite, within [``REFLECTANCE_MIN``,
                ``REFLECTANCE_MAX``] (up to ``REFLECTANCE_CEILING`` in at most ``REFLECTANCE_MAX_SHARE`` of its
                values), and non-negative unless ``negative="clip"``.
            config: each frame's configuration features in the model's order and units (``features``).
            out: optional preallocated (mask, score) arrays, bool and float32, C-contiguous, that receive the
                result (an onboard loop reuses them; their content is undefined if the call raises).
            negative: "error" (default) raises on negative reflectance; "clip" sets it to 0 (the caller's cube
                is not modified) and reports the count per frame as ``clipped_values``.
            min_reflectance: > 0: pixels whose mean reflectance over the bands is not above it are never skin
                (at the noise floor the indices are ratios of noise; e.g. 0.005 for ~3e-4 noise); 0 keeps the
                rules alone; None (default): the floor the model was evaluated with (``default_min_reflectance``,
                from its metadata).
            range_check: False leaves the share of values above ``REFLECTANCE_MAX`` and the bound
                ``REFLECTANCE_CEILING`` to the caller, who checks them over a whole frame cut into calls
                (``detect_file``'s row tiles, so that a cube in per cent gets its hint); the smallest value, NaN and
                negative values are still refused per call.

        Shape:
            cube: (B, 4, H, W); config: (B, k) (or (k,) for B = 1); out, mask, score: (B, H, W);
            out_of_domain, clipped_values: (B,).

        Returns:
            ``{"mask": bool, "score": float32 (positive inside), "out_of_domain": bool per frame}`` and, with
            ``negative="clip"``, ``"clipped_values"`` (int64 per frame). ``ValueError`` on invalid input.
        """
        if negative not in ("error", "clip"):
            raise ValueError(f"negative must be 'error' or 'clip', got {negative!r}")
        if min_reflectance is None:
            min_reflectance = self.default_min_reflectance
        if not (0.0 <= float(min_reflectance) < 1.0):
            raise ValueError(f"min_reflectance must lie in [0, 1), got {min_reflectance}")
        x = self._check_cube(cube)
        c, ood = self._config(config)
        if c.shape[0] != x.shape[0]:
            raise ValueError(f"config has {c.shape[0]} rows for a batch of {x.shape[0]} frames")
        B, _, H, W = x.shape
        n = H * W
        if out is not None:
            self._check_out(out, (B, H, W))
        clipped = np.zeros(B, dtype=np.int64) if negative == "clip" else None
        extra = {} if clipped is None else {"clipped_values": clipped}
        floor = x.shape[1] * float(min_reflectance)  # on the band sum
        if B * n <= self.tile:  # small frames: one call
            top = x.max()
            share = np.count_nonzero(x > REFLECTANCE_MAX) / x.size if top > REFLECTANCE_MAX else 0.0
            self._check_low(x.min(), top, clipped is not None, share if range_check else None)
            if clipped is not None:
                clipped += np.count_nonzero(x < 0, axis=(1, 2, 3))
                x = np.maximum(x, 0)
            mask, score = self.session.run(None, {"cube": np.ascontiguousarray(x), "config": c})
            if not np.isfinite(score.min()):
                self._check_low(np.nan)
            if floor > 0:
                mask &= x.sum(1) > floor
            if out is not None:
                out[0][...], out[1][...] = mask, score
                mask, score = out
            return {"mask": mask.astype(bool, copy=False), "score": score, "out_of_domain": ood, **extra}
        flat = x.reshape(B, self.n_bands, n)
        if out is not None:
            mask, score = out[0].reshape(B, n), out[1].reshape(B, n)
        else:
            mask, score = np.empty((B, n), dtype=bool), np.empty((B, n), dtype=np.float32)
        jobs = [(b, s, min(s + self.tile, n)) for b in range(B) for s in range(0, n, self.tile)]
        k = min(self.threads, len(jobs))
        counts = [np.zeros(B, dtype=np.int64) if clipped is not None else None for _ in range(k)]  # per worker
        queue, lock = iter(jobs), threading.Lock()

        def take() -> tuple[int, int, int] | None:  # workers pull the next tile: a worker that starts late simply takes fewer
            with lock:
                return next(queue, None)

        weights: dict[int, list[np.ndarray]] = {}  # per frame: its edge matrices as the head's weights

        def frame_weights(b: int) -> list[np.ndarray]:  # from the frame's configuration alone (batch 1, as the
            if b not in weights:  # whole graph), once per frame (two workers on a new frame: the same values)
                per_frame, head = cast(tuple, self._split)
                weights[b] = head.frame_weights(per_frame.run(None, {"config": c[b:b + 1]}))
            return weights[b]

        if self._split is not None:
            frame_weights(0)  # before the workers start, which all begin on frame 0
        if k > 1 and self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="torchskin-detect")
        futures = [cast("ThreadPoolExecutor", self._pool).submit(self._run_tiles, flat, c, mask, score, take, i,
                                                                 counts[i], floor, frame_weights)
                   for i in range(1, k)]
        ranges = []
        try:  # the calling thread is worker 0
            ranges.append(self._run_tiles(flat, c, mask, score, take, 0, counts[0], floor, frame_weights))
        finally:  # never return (or raise) while a worker still writes into the outputs
            ranges += [f.result() for f in futures]
        lows, highs, overs = zip(*ranges)
        # NaN propagates; the outputs are discarded: no mask comes back from an invalid cube
        self._check_low(np.min(lows), np.max(highs), clipped is not None,
                        sum(overs) / x.size if range_check else None)
        if clipped is not None:
            clipped += np.sum(cast(list[np.ndarray], counts), axis=0)
        if out is not None:
            return {"mask": out[0], "score": out[1], "out_of_domain": ood, **extra}
        return {"mask": mask.reshape(B, H, W), "score": score.reshape(B, H, W), "out_of_domain": ood, **extra}
