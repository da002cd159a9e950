"""The ``lut`` kind's model: a learned skin score baked into a table over the bands' coordinates and the
configuration (``LookupModel``), and the torch module its ``detector.onnx`` computes (``LookupDetector``)."""

from __future__ import annotations

import json
import lzma
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch
from torch import nn

from ...bands import INDEX_BANDS, INDEX_BANDS_NM, BandSet
from ..features import DIFFUSE_SHARE, FEATURES, config_buffers
from ..graphs import torch_detector_graph
from ..protocol import KindOption, PipelineRun
from .grid import COORDINATES, OCTAVE, cells, chain, check_geometry, config_bins, coordinates, flat_index

if TYPE_CHECKING:
    import onnx

    from ..protocol import CalibrationData

#: table levels per unit of the learner's raw score (log-odds): level = 128 + round(LEVELS_PER_LOGIT * score),
#: clipped to [0, 255], so a level step is 1/8 of a log-odds unit and the table spans scores -16 to +15.9
LEVELS_PER_LOGIT = 8.0
#: the level of log-odds 0 (even odds): no calibrated threshold lies below it
EVEN_ODDS_LEVEL = 128
#: the default earthlib margin (``train.earthlib_cells``; ``--earthlib-margin``): the cells the earthlib train spectra fall
#: in, not their neighbours. On the bits grid a one-step margin cost 0.015 of sunlit skin on ``make demo``'s fresh test
#: set (0.976 against 0.988) and 0.025 at sun >= 60 degrees; without it the three fresh sets still hold the scene
#: budget (docs/benchmarks.md)
EARTHLIB_MARGIN = 0
#: configuration bins per feature over the training domain: sun zenith, camera zenith and relative azimuth 15°, 15°
#: and 90° wide on the demo's domain, the diffuse share 0.25 wide. Measured on the demo's fresh test set (the learner
#: itself, its configuration snapped to bin centres, Pd sunlit mean over configurations at sun >= 60°): 30° camera
#: bins lost 0.027, 15° ones nothing; finer sun or azimuth bins gained nothing. Other features: one bin
CONFIG_BINS = {"sun_zenith_deg": 6, "camera_zenith_deg": 6, "relative_azimuth_deg": 2, DIFFUSE_SHARE: 4}


def config_counts_of(features: Sequence[str]) -> tuple[int, ...]:
    """The table's bins per configuration feature (``CONFIG_BINS``; 1 for a feature it does not name).

    >>> config_counts_of(["sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg", "diffuse_share"])
    (6, 6, 2, 4)
    """
    return tuple(CONFIG_BINS.get(f, 1) for f in features)


def to_levels(score: torch.Tensor) -> torch.Tensor:
    """Table levels (uint8) of raw scores (log-odds): ``EVEN_ODDS_LEVEL + round(LEVELS_PER_LOGIT * score)``,
    clipped to [0, 255].

    >>> to_levels(torch.tensor([-100.0, 0.0, 0.5, 100.0]))
    tensor([  0, 128, 132, 255], dtype=torch.uint8)
    """
    return (torch.round(score * LEVELS_PER_LOGIT) + EVEN_ODDS_LEVEL).clamp(0, 255).to(torch.uint8)


def _pack(data: bytes) -> torch.Tensor:
    """Bytes, LZMA-compressed, as a uint8 tensor (the checkpoint's form of the table: 300 M cells, most of them 0,
    take ~20 MB)."""
    return torch.frombuffer(bytearray(lzma.compress(data)), dtype=torch.uint8)


def _unpack(blob: torch.Tensor, dtype: Any, shape: Sequence[int]) -> torch.Tensor:
    return torch.from_numpy(np.frombuffer(lzma.decompress(blob.numpy().tobytes()), dtype=dtype).reshape(shape).copy())


class LookupModel(nn.Module):
    """Reflectance (N, n) and configuration (N, k) -> skin: a table of score levels (``levels``: one slice per
    configuration bin, one level per cell of the bands' coordinates, ``grid``), skin where the level reaches
    ``threshold``. The table is baked from a learner (``train.learn``) over all normalized differences,
    reflectances, brightness and the configuration; cells outside the training skin's support hold level 0.
    The configuration is the sun and camera angles and, by default, the sky's diffuse share
    (``features.DIFFUSE_SHARE``, a fourth input of ``detect``: ``--diffuse-share``).

    The ``lut`` detector kind (``protocol.DetectorModel``): ``decide`` looks pixels up, ``detector_graph`` is its
    ONNX export (``LookupDetector``: the table as one bit per cell, at the calibrated threshold),
    ``checkpoint`` / ``from_checkpoint`` its torch checkpoint (the table LZMA-compressed)."""

    kind: ClassVar[str] = "lut"
    methods: ClassVar[tuple[str, ...]] = ("lut",)
    #: any bands, at least two (``train.check_options``): the model keeps the dataset's (``bands``)
    required_bands: ClassVar[tuple[float, ...]] = ()
    options: ClassVar[tuple[KindOption, ...]] = (
        KindOption("bins", 0, "lut: cells per coordinate axis of the table (default 0: 32 for up to four bands, "
                              "fewer for more, the most that keeps 2^22 cells a slice: 21 for five, 12 for six)", int),
        KindOption("trees", 300, "lut: boosting rounds of the learner the table is baked from (default 300)", int),
        KindOption("support_dilation", 1, "lut: cells by which the training skin's support is widened; cells "
                                          "outside it are never skin (default 1)", int),
        KindOption("earthlib_margin", EARTHLIB_MARGIN, "lut: cells within this many steps of an earthlib train "
                                                       "spectrum (at any brightness) are never skin; 0: the cells "
                                                       "it falls in; -1: no margin (default 0)", int),
        KindOption("max_rows", 3_000_000, "lut: at most this many training rows (a seeded draw; default "
                                          "3000000)", int),
        KindOption("configuration", True, "lut: learn without the configuration (one table for every sun and "
                                          "camera: what the configuration is worth)", bool, "--no-configuration"),
        KindOption("diffuse_share", True, "lut: leave the sky's share of the light (diffuse_share, measured by a "
                                          "sunlit and a shaded panel) out of the configuration: sun and camera "
                                          "angles only, as the other kinds", bool, "--no-diffuse-share"))
    method_help: ClassVar[str] = ("lut: gradient-boosted trees on every normalized difference, reflectance, "
                                  "brightness and the configuration, baked into a table looked up per pixel")
    #: onboard, the table is looked up with numpy (``onboard.lut.LutHead``); the graph runs as it is elsewhere. On a
    #: 1 MP frame (2 cores) the head takes ~1.2x the box detector and ~4x the frame-read floor, within issue 40's 2x
    #: and 5x (docs/benchmarks.md): ``make demo`` may ship it
    onboard_head: ClassVar[str] = "lut"
    onboard_selectable: ClassVar[bool] = True
    card_score: ClassVar[str] = "the lookup table: 1 inside the calibrated region, 0 outside (a table holds decisions)"
    pipeline_runs: ClassVar[tuple[PipelineRun, ...]] = (PipelineRun("lut", ("--method", "lut")),)
    card_use: ClassVar[str] = (
        "Onboard skin detection in reflectance imagery of the model's bands (metadata `bands`) with a configuration-"
        "dependent lookup table over the log ratios of neighbouring bands and a brightness "
        "(`torchskin.detectors.lut`), calibrated to the false-alarm budget.")

    # buffers (declared for type checkers; ``register_buffer`` creates them)
    levels: torch.Tensor
    threshold: torch.Tensor
    floor_level: torch.Tensor
    shift: torch.Tensor
    lo: torch.Tensor
    cfg_lo: torch.Tensor
    cfg_inv: torch.Tensor
    domain: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor

    def __init__(self, n_bands: int = 4, bins: int = 32, features: Sequence[str] = FEATURES,
                 config_counts: Sequence[int] | None = None, domain: Any = None, bands: BandSet | None = None):
        super().__init__()
        if bands is None and n_bands != len(INDEX_BANDS_NM):
            raise ValueError(f"a {n_bands}-band table needs its bands (the index bands are four)")
        #: the bands the table reads, in the cube's order (the export's metadata ``bands``)
        self.bands = INDEX_BANDS if bands is None else bands
        if len(self.bands) != n_bands:
            raise ValueError(f"bands holds {len(self.bands)} bands for a {n_bands}-band table")
        self.features = tuple(features)
        config_counts = config_counts_of(self.features) if config_counts is None else config_counts
        if len(config_counts) != len(self.features):
            raise ValueError(f"config_counts needs one count per feature ({len(self.features)}), got {config_counts}")
        if not 2 <= bins <= 255:
            raise ValueError(f"bins must lie in [2, 255], got {bins}")
        self.n_bands, self.bins, self.config_counts = int(n_bands), int(bins), tuple(int(c) for c in config_counts)
        mean, std, dom = config_buffers(self.features, None, None, domain)
        self.register_buffer("mean", mean)  # unused (the protocol's standardisation): the table takes raw angles
        self.register_buffer("std", std)
        self.register_buffer("domain", dom)
        width = (dom[:, 1] - dom[:, 0]).clamp_min(1e-6)
        self.register_buffer("cfg_lo", dom[:, 0].clone())
        self.register_buffer("cfg_inv", torch.tensor(self.config_counts, dtype=torch.float32) / width)
        #: each axis's cell width, 2^shift coordinate units (``grid``), and its first cell, in those widths
        self.register_buffer("shift", torch.full((n_bands,), 20, dtype=torch.int32))
        self.register_buffer("lo", torch.zeros(n_bands, dtype=torch.int32))
        self.lo[0] = 127 * OCTAVE >> 20  # the brightness from reflectance 1 (until ``set_range``)
        #: the reference band (``grid``): the brightness axis, and the band every log ratio chains towards
        self.ref = n_bands - 1
        self.register_buffer("levels", torch.zeros(math.prod(self.config_counts), bins ** n_bands, dtype=torch.uint8))
        self.register_buffer("threshold", torch.tensor(255, dtype=torch.int32))
        #: the lowest threshold any calibration may set: even odds, and the earthlib train budget (``train``)
        self.register_buffer("floor_level", torch.tensor(EVEN_ODDS_LEVEL, dtype=torch.int32))
        self.boosters: list[str] = []  # the learners (LightGBM text) whose mean score the table holds, [] when unknown
        self.config_inputs = True  # whether the learner took the configuration (``--no-configuration``: not)

    def slices(self, config: torch.Tensor) -> torch.Tensor:
        """The table slice (N,) of configurations (N, k)."""
        return config_bins(config.float(), self.cfg_lo, self.cfg_inv, self.config_counts)

    def set_range(self, ref: int, shift: Sequence[int], lo: Sequence[int]) -> None:
        """Set the reference band, each axis's cell width (2^shift units) and first cell; ``ValueError`` for a
        geometry in which a band at 0 would not land in an edge cell (``grid.check_geometry``)."""
        if not 0 <= ref < self.n_bands:
            raise ValueError(f"the reference band must lie in [0, {self.n_bands}), got {ref}")
        check_geometry(shift, lo, self.bins)
        self.ref = int(ref)
        self.shift.copy_(torch.as_tensor(shift, dtype=torch.int32))
        self.lo.copy_(torch.as_tensor(lo, dtype=torch.int32))

    def cells_of(self, R: torch.Tensor) -> torch.Tensor:
        """The cell (N,) of reflectance (N, n) (float32, as every backend computes it)."""
        return cells(coordinates(R.float(), self.ref), self.shift, self.lo, self.bins)

    @torch.no_grad()
    def level(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        """The table level (N,) int32 of each pixel (a pixel with a band at 0 lands in an edge cell: level 0)."""
        R, config = torch.as_tensor(R, dtype=torch.float32), torch.as_tensor(config, dtype=torch.float32)
        return self.levels[self.slices(config), self.cells_of(R)].int()

    @torch.no_grad()
    def decide(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        """Skin mask (N,) of reflectance (N, n) under configurations (N, k): the level reaches the threshold."""
        return self.level(R, config) >= self.threshold

    def mask_bits(self) -> torch.Tensor:
        """The calibrated table, one bit per cell (little-endian within a byte), (slices * cells / 8,) uint8."""
        on = (self.levels >= self.threshold.to(torch.uint8)).reshape(-1).numpy()
        return torch.from_numpy(np.packbits(on, bitorder="little"))

    # --------------------------------------------------------------------- the detector kind (protocol.DetectorModel)
    def detector_graph(self, meta: dict[str, str]) -> onnx.ModelProto:
        """``detector.onnx`` of the table (``LookupDetector``), with metadata ``meta`` and the grid (``lut_grid``)."""
        return torch_detector_graph(LookupDetector(self), len(self.features), {**meta, "lut_grid": self.grid_json()},
                                    self.n_bands)

    def grid_json(self) -> str:
        """The table's geometry as JSON (bins, shift, lo, config lo/inv/counts): the onboard head's parameters."""
        f32 = lambda t: [float(v) for v in t.float().tolist()]  # noqa: E731  (float32 values, exact in JSON)
        return json.dumps({"coordinates": COORDINATES, "bins": self.bins, "n_bands": self.n_bands, "ref": self.ref,
                           "shift": [int(v) for v in self.shift], "lo": [int(v) for v in self.lo],
                           "cfg_lo": f32(self.cfg_lo), "cfg_inv": f32(self.cfg_inv),
                           "config_counts": list(self.config_counts)})

    def reference_detector(self) -> nn.Module:
        """The torch module ``detector.onnx`` computes (``LookupDetector``)."""
        return LookupDetector(self)

    def checkpoint(self, meta: dict) -> dict:
        """Grid buffers, the table and the learner (LZMA-compressed), sizes and metadata."""
        small = {k: v for k, v in self.state_dict().items() if k != "levels"}
        return {"state_dict": small, "levels_xz": _pack(self.levels.contiguous().numpy().tobytes()), "features": list(self.features),
                "n_bands": self.n_bands, "bins": self.bins, "config_counts": list(self.config_counts),
                "booster_xz": _pack(json.dumps(self.boosters).encode()), "config_inputs": self.config_inputs, "ref": self.ref,
                "coordinates": COORDINATES, "bands": self.bands.to_json(), "meta": meta}

    @classmethod
    def from_checkpoint(cls, ck: dict) -> LookupModel:
        """The model of a checkpoint dict (eval mode); ``ValueError`` for a checkpoint of another kind."""
        if ck.get("kind") != "lut":
            raise ValueError("not a lut checkpoint")
        if ck.get("coordinates") != COORDINATES:
            raise ValueError(f"its table was built on other coordinates ({ck.get('coordinates', 'fourth-root brightness')}"
                             f", not {COORDINATES}: an earlier torchskin); train it again with this one")
        try:  # checkpoints before the bands were kept: the index bands
            bands = BandSet.from_json(ck["bands"]) if "bands" in ck else None
        except ValueError as e:
            raise ValueError(f"its bands are damaged ({e})") from None
        m = cls(ck["n_bands"], ck["bins"], ck["features"], ck["config_counts"], bands=bands)
        state = dict(ck["state_dict"])
        try:
            state["levels"] = _unpack(ck["levels_xz"], np.uint8, m.levels.shape)
            text = lzma.decompress(ck["booster_xz"].numpy().tobytes()).decode()
            m.boosters = json.loads(text) if text.startswith("[") else [text] if text else []  # one, before ensembles
        except (lzma.LZMAError, ValueError, UnicodeDecodeError) as e:  # json's errors are ValueErrors
            raise ValueError(f"its table or learner is damaged ({e})") from None
        m.load_state_dict(state)
        m.config_inputs = bool(ck.get("config_inputs", True))
        m.ref = int(ck.get("ref", m.n_bands - 1))
        return m.eval()

    def calibrate_to_budget(self, data: CalibrationData, scene_budget: float, pfa_budget: float,
                            iters: int = 30) -> dict:
        """``evaluation.calibrate_to_budget``: the lowest threshold level at which at most ``scene_budget`` of the
        non-skin rows (the bright ones can pass) are called skin, never below ``floor_level`` (even odds and the
        earthlib train budget, set by training). Unlike the box scale, it may fall below the training threshold:
        training holds the scene budget on the training scene, the calibration on the held-out one."""
        nonskin, bright = data.nonskin, data.bright
        lv = self.level(data.R[nonskin & bright], data.X[nonskin & bright])
        before = int(self.threshold)
        allowed = int(math.floor(scene_budget * int(nonskin.sum())))
        top = lv.sort(descending=True).values
        need = int(top[allowed]) + 1 if allowed < top.numel() else 0
        self.threshold.fill_(min(255, max(int(self.floor_level), need)))
        rate = float((self.decide(data.R[nonskin], data.X[nonskin]) & bright[nonskin]).float().mean())
        return {"knob": "threshold level", "before": float(before), "after": float(self.threshold),
                "pfa_scene": rate}

    @staticmethod
    def card_false_alarms(train: dict, f: Any) -> str:
        """The model card's account of the threshold (``train.tune_threshold``)."""
        return (f"the table's threshold was raised to level {f(train.get('threshold'))} so that at most "
                f"{f(train.get('pfa_budget'))} of the earthlib *train* spectra are called skin in every configuration "
                f"slice, and at most {f(train.get('scene_budget'))} of the training scene's non-skin pixels")


class LookupDetector(nn.Module):
    """``detector.onnx`` for a ``LookupModel``: cube (B, n, H, W) + configuration (B, k) -> mask and score
    (B, H, W), score 1 (skin) or 0. Per frame the configuration picks a table slice; per pixel the coordinates
    pick a cell, whose bit (the calibrated table, ``LookupModel.mask_bits``) is the decision.

    The graph has no bit cast (not before ONNX opset 26), so it computes each band's float32 bit pattern from its
    value (``float_bits``: exponent from a logarithm, corrected against exact powers of two, and mantissa), exactly:
    every pixel lands in the cell the torch model and the onboard head (which reads the bits) give it."""

    bits: torch.Tensor
    pow2: torch.Tensor
    exp2: torch.Tensor
    scale: torch.Tensor
    lo: torch.Tensor
    cfg_lo: torch.Tensor
    cfg_inv: torch.Tensor

    def __init__(self, model: LookupModel):
        super().__init__()
        self.n, self.bins, self.counts = model.n_bands, model.bins, model.config_counts
        self.cells = model.bins ** model.n_bands
        self.ref = model.ref
        self.register_buffer("bits", model.mask_bits())
        self.register_buffer("pow2", torch.tensor([1, 2, 4, 8, 16, 32, 64, 128], dtype=torch.int32))
        #: 2^k for k = -127 .. 128 (2^128: inf), exact in float32
        self.register_buffer("exp2", torch.exp2(torch.arange(-127, 129, dtype=torch.float64)).float())
        self.register_buffer("scale", torch.exp2(-model.shift.double()).reshape(-1, 1))  # (n, 1): 2^-shift
        self.register_buffer("lo", model.lo.double().reshape(-1, 1))
        for name in ("cfg_lo", "cfg_inv"):
            self.register_buffer(name, getattr(model, name).clone())

    def float_bits(self, x: torch.Tensor) -> torch.Tensor:
        """The float32 bit pattern (int64) of ``x`` (float32) computed with float operations, exactly for finite
        x >= 0 below 2^64. NaN and negative values give 0 (they, like 0, land in an edge cell either way), larger
        values 2^64's pattern (beyond every brightness axis)."""
        x = torch.where(x > 0, x, torch.zeros_like(x)).clamp(max=2.0 ** 64)  # NaN > 0 is false
        tiny = 2.0 ** -126
        xn = x.clamp(min=tiny)
        e = torch.floor(torch.log2(xn)).clamp(-126, 64)  # within one of the exponent
        p = self.exp2[(e + 127).long()]
        e = e - (xn < p).float() + (xn >= 2 * p).float()
        m = xn / self.exp2[(e + 127).long()]  # [1, 2): exact, a division by a power of two
        normal = (e.long() + 127) * OCTAVE + ((m - 1) * OCTAVE).long()
        sub = (x * 2.0 ** 126 * OCTAVE).long()  # below 2^-126: the pattern is x / 2^-149
        return torch.where(x >= tiny, normal, sub)

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mask and score (B, H, W) of a reflectance cube (B, n, H, W) under configurations (B, k)."""
        B, n, H, W = cube.shape
        b = self.float_bits(cube.reshape(B, n, H * W))  # (B, n, HW)
        V = chain(b, self.ref, dim=1).double()  # the coordinates (``grid``), bands along axis 1
        q = torch.floor(V * self.scale)  # exact: below 2^53, times a power of two
        cell = flat_index(q, self.lo, self.bins, dim=1)
        slice_ = config_bins(config, self.cfg_lo, self.cfg_inv, self.counts)  # (B,)
        flat = slice_[:, None] * self.cells + cell.long()
        byte = self.bits[torch.div(flat, 8, rounding_mode="floor")].to(torch.int32)
        bit = torch.remainder(torch.div(byte, self.pow2[torch.remainder(flat, 8)], rounding_mode="floor"), 2)
        mask = bit > 0
        score = mask.float()
        return mask.reshape(B, H, W), score.reshape(B, H, W)


__all__ = ["CONFIG_BINS", "EARTHLIB_MARGIN", "config_counts_of", "EVEN_ODDS_LEVEL", "LEVELS_PER_LOGIT", "LookupDetector", "LookupModel", "to_levels"]
