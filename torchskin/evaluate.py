"""Evaluate skin detectors on held-out configurations and on the earthlib test partition, side by side: the
static thesis box, learned box models (checkpoints or ``boundaries.onnx`` / ``baseline_box.onnx``), the
configuration-conditioned classifier and any exported ``detector.onnx``. Detection probability Pd of skin
pixels (sunlit, glint-affected, shadowed), false-alarm probability Pfa (test spectra inside each
configuration's decision region, and the scene's non-skin pixels, also by confuser family), each model's
decision-region area in the (NDGRI, NDSI) plane per configuration, overall and per (sun zenith x camera
zenith) bin; ROC curves, a Pd heat map and a comparison figure as PNG."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import torch
from numpy.typing import ArrayLike

from .angles import BACKLIT_MIN_DEG
from .bands import INDEX_BANDS_NM
from .dataset.files import manifest, read_rows
from .detect import DEFAULT_BOX
from .detectors import registry
from .detectors.boxes import false_alarm_rate, inside_box
from .detectors.features import BAND_COLUMNS, FEATURES, confuser_indices, ratio_indices
from .detectors.features import MIN_REFLECTANCE as _MIN_REFLECTANCE
from .detectors.protocol import CalibrationData, DetectorModel

#: one model path or several (``load_candidate``)
ModelPaths = str | os.PathLike | Sequence[str | os.PathLike]
SUN_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
CAMERA_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
#: a sunlit skin pixel is glint-affected when the specular lobe adds at least this much apparent reflectance
#: (π f_s) at 1580 nm (section 3.3.3 parameters): enough to move NDSI by about 0.02 or more
GLINT_REFLECTANCE = 0.01
#: index-plane grid (per axis, over [-1, 1]) on which the decision region of a non-box model is measured
AREA_GRID = 64
#: brightness floor of the evaluation protocol, applied to every model alike (``detectors.features.MIN_REFLECTANCE``)
MIN_REFLECTANCE = _MIN_REFLECTANCE


@dataclass
class Candidate:
    """A detector under evaluation: ``decide(R (n, 4), X (n, k)) -> (n,) bool`` on ELM reflectance at 544, 633,
    1080, 1580 nm and configuration features; ``boxes(X) -> (n, 4)`` for box models (None otherwise)."""

    name: str
    kind: str  # "static", "detector" (a detector.onnx), "boxes" (also boundaries.onnx) or a checkpoint's kind
    features: list[str]
    decide: Callable
    boxes: Callable | None = None
    path: str = ""
    meta: dict = field(default_factory=dict)


def _box_decide(boxes_of):
    def decide(R, X):
        g, s, v = ratio_indices(R)
        return inside_box(boxes_of(X), g, s, v)
    return decide


def static_candidate() -> Candidate:
    """The thesis's diffuse-model box, the same at every configuration."""
    box = torch.tensor([DEFAULT_BOX.b1, DEFAULT_BOX.b2, DEFAULT_BOX.c1, DEFAULT_BOX.c2])
    boxes_of = lambda X: box.expand(X.shape[0], 4)  # noqa: E731
    return Candidate("static box (thesis)", "static", list(FEATURES), _box_decide(boxes_of), boxes_of, "static")


def load_candidate(spec: str | os.PathLike) -> Candidate:
    """A candidate from a path: a torch checkpoint (.pt: boundary boxes or a classifier), an exported
    ``boundaries.onnx`` / ``baseline_box.onnx`` (configuration -> boxes) or a ``detector.onnx`` (cube +
    configuration -> mask), or the word "static"."""
    from pathlib import Path

    p = str(spec)
    if p == "static":
        return static_candidate()
    if Path(p).is_dir():
        what = " (a dataset: pass it as --data)" if (Path(p) / "_manifest.json").is_file() else ""
        raise ValueError(f"--model {p!r} is a folder{what}; a model file (.pt or .onnx) or 'static' is expected")
    if not Path(p).is_file():
        raise ValueError(f"--model {p!r} does not exist")
    name = Path(p).name
    if p.endswith(".onnx"):
        from .onboard import OnboardBoxes, OnboardDetector, model_inputs

        if "cube" in model_inputs(p):
            d = OnboardDetector(p)
            decide = lambda R, X: torch.from_numpy(d.pixels(R.numpy(), X.numpy())["mask"])  # noqa: E731
            return Candidate(name, "detector", list(d.features), decide, None, p, dict(d.meta))
        b = OnboardBoxes(p)
        boxes_of = lambda X: torch.from_numpy(b(np.asarray(X, dtype=np.float32))["boxes"])  # noqa: E731
        return Candidate(name, "boxes", list(b.features), _box_decide(boxes_of), boxes_of, p, dict(b.meta))
    model, ck = registry.load(p)
    return model_candidate(model, name, p, ck.get("meta", {}))


def model_candidate(model: DetectorModel, name: str, path: str = "", meta: dict | None = None) -> Candidate:
    """A candidate of a detector model of any registered kind (``detectors.registry``): its ``decide`` and, for a
    box kind, its ``boxes``."""
    return Candidate(name, registry.kind_of(model), list(model.features), model.decide, registry.boxes_of(model),
                     path, meta or {})


def load_model(path: str | os.PathLike, what: str = "model") -> tuple[DetectorModel, dict]:
    """The model of a torchskin checkpoint (by the checkpoint's ``kind``: ``detectors.registry.load``) and the
    checkpoint dict; ``ValueError`` with one line naming ``what`` and the file for anything else."""
    return registry.load(path, what)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """The dict of a torchskin model checkpoint (``ValueError`` with one line for anything else;
    ``detectors.registry.load_checkpoint``)."""
    return registry.load_checkpoint(path)


def box_function(model_path: str | os.PathLike) -> tuple[list[str], Callable]:
    """``features (N, k) -> boxes (N, 4)`` from a torch checkpoint (.pt) or an exported boundaries.onnx."""
    c = load_candidate(model_path)
    if c.boxes is None:
        raise ValueError(f"{str(model_path)!r} is not a box model (it has no per-configuration boxes)")
    return c.features, c.boxes


def glint_affected(theta_i_deg: ArrayLike, theta_r_deg: ArrayLike, delta_phi_deg: ArrayLike) -> torch.Tensor:
    """Whether the specular lobe (eq 2.3.4, section 3.3.3 parameters at 1580 nm) adds at least
    ``GLINT_REFLECTANCE`` apparent reflectance π f_s at these local angles (degrees)."""
    from .optics import THESIS_SPECULAR, microfacet_brdf

    d = math.pi / 180
    sig, rho0 = THESIS_SPECULAR.at(torch.tensor([1580.0], dtype=torch.float64))
    f = microfacet_brdf(torch.as_tensor(theta_i_deg, dtype=torch.float64) * d,
                        torch.as_tensor(theta_r_deg, dtype=torch.float64) * d,
                        torch.as_tensor(delta_phi_deg, dtype=torch.float64) * d, sig[0], rho0[0])
    return math.pi * f >= GLINT_REFLECTANCE


def _families(col: dict) -> np.ndarray:
    """Per row, the family of what a non-skin pixel shows: "ground", "clothing: <earthlib class>",
    "confuser: <earthlib class>" (datasets written before the material column: confusers and "other")."""
    from .confusers import family

    n = len(col["label"])
    conf = col.get("confuser")
    mat = col.get("material")
    cloth = col.get("clothing")
    out = np.full(n, "other", dtype=object)
    cache: dict[str, str] = {}

    def fam(name):
        if name not in cache:
            try:
                cache[name] = family(name)
            except ValueError:
                cache[name] = "unknown"
        return cache[name]

    if mat is not None:
        out[mat == "ground"] = "ground"
        out[mat == "clothing"] = "clothing: fixed spectrum"
        if cloth is not None:
            for nm in np.unique(cloth[(mat == "clothing") & (cloth != "")]):
                out[(mat == "clothing") & (cloth == nm)] = "clothing: " + fam(nm)
    if conf is not None:
        for nm in np.unique(conf[conf != ""]):
            out[conf == nm] = "confuser: " + fam(nm)
    return out


ROC_SCALES = tuple(float(x) for x in np.linspace(0.25, 3.0, 23))


class _Rows:
    """The held-out rows a model is judged on, with their configurations and categories."""

    def __init__(self, data_dir, features):
        cols = list(dict.fromkeys([*features, "sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg",
                                   "label", "shadow", "ndgri", "ndsi", "group", "sun", "skin", *BAND_COLUMNS,
                                   "theta_i_deg", "theta_r_deg", "delta_phi_deg"]))
        rows = read_rows(data_dir, cols, optional=("material", "confuser", "clothing"))  # checks the folder, columns
        self.excluded = rows.excluded
        if len(rows) == 0:
            raise ValueError(f"no rows with a valid ELM in {str(data_dir)!r}")
        self.n = len(rows)
        col = rows.columns
        self.X = torch.from_numpy(rows.stack(features, np.float32))
        self.R = torch.from_numpy(rows.bands(np.float32))
        self.g, self.s = torch.from_numpy(col["ndgri"]).float(), torch.from_numpy(col["ndsi"]).float()
        self.v = torch.from_numpy(rows.index("ndvn", np.float32))  # float32, as ratio_indices(self.R)
        self.label = torch.from_numpy(col["label"]).bool()
        self.shadow = torch.from_numpy(col["shadow"]).bool()
        self.glint = glint_affected(col["theta_i_deg"], col["theta_r_deg"], col["delta_phi_deg"]) & ~self.shadow
        self.sz = torch.from_numpy(col["sun_zenith_deg"]).float()
        self.cz = torch.from_numpy(col["camera_zenith_deg"]).float()
        self.ra = torch.from_numpy(col["relative_azimuth_deg"]).float()
        self.backlit = self.ra >= BACKLIT_MIN_DEG  # the camera looks towards the sun (the generator's rule)
        keys = torch.from_numpy(np.stack([col["group"], col["sun"], col["skin"]], -1).astype(np.int64))
        _, self.cfg = torch.unique(keys, dim=0, return_inverse=True)  # configuration id per row
        self.n_cfg = int(self.cfg.max()) + 1
        self.first = torch.full((self.n_cfg,), self.n, dtype=torch.long).scatter_reduce(
            0, self.cfg, torch.arange(self.n), "amin")  # a row of each configuration
        self.cfg_X = self.X[self.first]  # (configs, k)
        self.family = _families(col)
        self.features = list(features)


def _cfg_mean(values: torch.Tensor, cfg: torch.Tensor, n_cfg: int) -> float:
    """Mean over configurations of the per-configuration mean of ``values`` (rows of ``cfg``)."""
    if values.numel() == 0:
        return float("nan")
    s = torch.zeros(n_cfg, dtype=torch.float64).index_add_(0, cfg, values.double())
    c = torch.zeros(n_cfg, dtype=torch.float64).index_add_(0, cfg, torch.ones_like(values, dtype=torch.float64))
    return float((s[c > 0] / c[c > 0]).mean())


def _rate(hit: torch.Tensor, m: torch.Tensor) -> float:
    return float(hit[m].float().mean()) if bool(m.any()) else float("nan")


class _Judged:
    """One model's decisions on the rows, its earthlib-test Pfa and region area per configuration."""

    def __init__(self, cand: Candidate, rows: _Rows, test_R: torch.Tensor, test_pts: torch.Tensor, floor: float):
        if cand.features != rows.features:
            raise ValueError(f"{cand.name} takes features {cand.features}, the rows hold {rows.features}")
        cfg_X = rows.cfg_X
        self.hit = cand.decide(rows.R, rows.X).bool() & (rows.R.mean(-1) > floor)
        bright = test_R.mean(-1) > floor
        if cand.boxes is not None:
            bx = cand.boxes(cfg_X)
            pts = torch.where(bright[:, None], test_pts, torch.full_like(test_pts, math.nan))  # aligned with test_R
            self.pfa_cfg = false_alarm_rate(bx, pts).double()
            w = (bx[:, 1].clamp(-1, 1) - bx[:, 0].clamp(-1, 1)).clamp_min(0)
            h = (bx[:, 3].clamp(-1, 1) - bx[:, 2].clamp(-1, 1)).clamp_min(0)
            self.area_cfg = (w * h).double()
        else:
            self.pfa_cfg = _pfa_by_config(cand, cfg_X, test_R, bright)
            self.area_cfg = _grid_area(cand, cfg_X, rows)

    def summary(self, rows: _Rows, m: torch.Tensor | None = None) -> dict:
        m = torch.ones_like(rows.label) if m is None else m
        sk = rows.label & m
        lit = sk & ~rows.shadow
        cfgs = torch.unique(rows.cfg[m]) if bool(m.any()) else torch.zeros(0, dtype=torch.long)
        nonskin = ~rows.label & m
        return {"pd": _rate(self.hit, sk), "pd_sunlit": _rate(self.hit, lit),
                "pd_sunlit_mean_over_configs": _cfg_mean(self.hit[lit].float(), rows.cfg[lit], rows.n_cfg),
                "pd_sunlit_no_glint": _rate(self.hit, lit & ~rows.glint), "pd_glint": _rate(self.hit, lit & rows.glint),
                "pd_shadow": _rate(self.hit, sk & rows.shadow),
                "pd_backlit": _rate(self.hit, sk & rows.backlit),
                "pd_backlit_sunlit": _rate(self.hit, lit & rows.backlit),
                "pfa": float(self.pfa_cfg[cfgs].mean()) if cfgs.numel() else float("nan"),
                "pfa_scene": _rate(self.hit, nonskin),
                "pfa_scene_sunlit": _rate(self.hit, nonskin & ~rows.shadow),
                "pfa_scene_shadow": _rate(self.hit, nonskin & rows.shadow),
                "area_mean": float(self.area_cfg[cfgs].mean()) if cfgs.numel() else float("nan"),
                "skin_pixels": int(sk.sum()), "sunlit_skin_pixels": int(lit.sum()),
                "shadow_skin_pixels": int((sk & rows.shadow).sum()), "backlit_skin_pixels": int((sk & rows.backlit).sum()),
                "nonskin_pixels": int(nonskin.sum()),
                "glint_pixels": int((lit & rows.glint).sum())}

    def scene_by_family(self, rows: _Rows) -> dict:
        """Per material family of the non-skin pixels: Pfa (and pixels) overall, in sun, in shadow, and in
        back-lit configurations."""
        out = {}
        nonskin = (~rows.label).numpy()
        shadow = rows.shadow.numpy()
        backlit = rows.backlit.numpy()
        hit = self.hit.numpy()
        for fam in np.unique(rows.family[nonskin]):
            sel = nonskin & (rows.family == fam)
            e = {"pfa": float(hit[sel].mean()), "pixels": int(sel.sum())}
            for name, m in (("sunlit", sel & ~shadow), ("shadow", sel & shadow), ("backlit", sel & backlit)):
                e[f"pfa_{name}"] = float(hit[m].mean()) if m.any() else float("nan")
                e[f"pixels_{name}"] = int(m.sum())
            out[str(fam)] = e
        return out


def _pfa_by_config(cand: Candidate, cfg_X: torch.Tensor, test_R: torch.Tensor, bright: torch.Tensor,
                   chunk: int = 1 << 20) -> torch.Tensor:
    """Per configuration, the fraction of the earthlib test spectra (reflectance (m, 4), as measured) that the
    model calls skin (only ``bright`` ones can be)."""
    m = test_R.shape[0]
    out = torch.empty(cfg_X.shape[0], dtype=torch.float64)
    per = max(1, chunk // m)
    for lo in range(0, cfg_X.shape[0], per):
        c = cfg_X[lo:lo + per]
        X = c.repeat_interleave(m, 0)
        R = test_R.repeat(c.shape[0], 1)
        out[lo:lo + c.shape[0]] = (cand.decide(R, X).reshape(c.shape[0], m) & bright).double().mean(1)
    return out


def _grid_area(cand: Candidate, cfg_X: torch.Tensor, rows: _Rows) -> torch.Tensor:
    """Per configuration, the area of the (NDGRI, NDSI) plane (over [-1, 1]^2) that the model calls skin, at
    the band-pair brightness of that configuration's sunlit skin (median (g + r) / 2 and (n + s) / 2)."""
    lit = rows.label & ~rows.shadow
    pair = torch.stack([(rows.R[:, 0] + rows.R[:, 1]) / 2, (rows.R[:, 2] + rows.R[:, 3]) / 2], -1)
    default = pair[lit].median(0).values if bool(lit.any()) else torch.tensor([0.4, 0.3])
    med = default.expand(rows.n_cfg, 2).clone()
    order = torch.argsort(rows.cfg[lit], stable=True)
    cfg_l, pair_l = rows.cfg[lit][order], pair[lit][order]
    uniq, counts = torch.unique_consecutive(cfg_l, return_counts=True)
    for c, part in zip(uniq.tolist(), torch.split(pair_l, counts.tolist())):  # per configuration (not per pixel)
        med[c] = part.median(0).values
    k = AREA_GRID
    axis = -1 + (torch.arange(k) + 0.5) * (2.0 / k)
    G, S = torch.meshgrid(axis, axis, indexing="ij")
    G, S = G.reshape(-1), S.reshape(-1)
    out = torch.empty(rows.n_cfg, dtype=torch.float64)
    per = max(1, (1 << 20) // (k * k))
    for lo in range(0, rows.n_cfg, per):
        a = med[lo:lo + per]  # (c, 2)
        n = a.shape[0]
        R = torch.stack([a[:, :1] * (1 + G), a[:, :1] * (1 - G), a[:, 1:] * (1 + S), a[:, 1:] * (1 - S)], -1)
        X = cfg_X[lo:lo + per].repeat_interleave(k * k, 0)
        hit = cand.decide(R.reshape(-1, 4).float(), X).reshape(n, k * k)
        out[lo:lo + n] = hit.double().mean(1) * 4.0
    return out


#: a model's or a dataset's world: the skin surface model of the renders and the light model (``world_of``)
WORLD_LABELS = {"surface": "skin surface model", "light_model": "light model"}


def model_world(path: str | os.PathLike) -> dict[str, str]:
    """The world a model was trained in, as far as its file records it: ``surface`` and ``light_model`` from a
    checkpoint's training summary, or ``skin_surface_model`` (and ``light_model``) from an ONNX export's metadata;
    {} for "static" (the thesis's box belongs to no dataset)."""
    p = str(path)
    if p == "static":
        return {}
    if p.endswith(".onnx"):
        import onnxruntime as ort

        meta = ort.InferenceSession(p, providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
        world = {"surface": meta.get("skin_surface_model", ""), "light_model": meta.get("light_model", "")}
    else:
        train = registry.load_checkpoint(p).get("meta", {})
        world = {"surface": str(train.get("surface", "")), "light_model": str(train.get("light_model", ""))}
    return {k: v for k, v in world.items() if v}


def dataset_world(data_dir: str | os.PathLike) -> dict[str, str]:
    """The world a dataset was rendered in (its manifest: the skin surface model and the light model)."""
    from .dataset.files import dataset_surface

    world = {"surface": dataset_surface(data_dir), "light_model": str((manifest(data_dir) or {}).get("light_model", ""))}
    return {k: v for k, v in world.items() if v}


def world_warnings(data_dir: str | os.PathLike, model_paths: Sequence[str | os.PathLike]) -> list[str]:
    """One sentence per model whose recorded world (``model_world``) differs from the dataset's
    (``dataset_world``): its figures on these data describe another world than the one it was trained in."""
    data = dataset_world(data_dir)
    out = []
    for path in model_paths:
        own = model_world(path)
        diff = [f"{WORLD_LABELS[k]} {own[k]} (the data: {data[k]})" for k in WORLD_LABELS
                if k in own and k in data and own[k] != data[k]]
        if diff:
            out.append(f"{path} was trained under another world than {data_dir}: " + ", ".join(diff)
                       + "; its figures here do not describe the world it was made for")
    return out


def evaluate(data_dir: str | os.PathLike, model_paths: ModelPaths, scales: Sequence[float] = ROC_SCALES,
             min_reflectance: float = MIN_REFLECTANCE) -> dict:
    """Every model of ``model_paths`` and the static box on the held-out dataset at ``data_dir``, all under the
    brightness floor ``min_reflectance``: Pd of skin pixels (sunlit, glint-affected, shadowed), Pfa on the
    earthlib test spectra and on the scene's non-skin pixels, decision-region areas, overall, at sun zenith >=
    60° and per (sun zenith x camera zenith) bin, and, when the first model has boxes, its ROC.

    Args:
        data_dir: a generated dataset folder (``torchskin generate``; rows of frames with a valid ELM).
        model_paths: one path or a list (see ``load_candidate``: .pt checkpoints, boundaries.onnx /
            baseline_box.onnx, detector.onnx, or "static"); all must take the same features.
        scales: the box scale factors of the ROC (``ROC_SCALES``).
        min_reflectance: the brightness floor, in [0, 1) (``MIN_REFLECTANCE``).

    Returns:
        A JSON-ready dict: ``models`` (one entry per model, the static box last: name, path, kind, overall,
        sun_zenith_ge_60, bins, area, scene_pfa_by_family), ``learned`` / ``static`` (and ``bins``,
        ``sun_zenith_ge_60``, ``roc``) comparing the first model with the static box, and the dataset's
        features, rows, rows_excluded_no_sunlit_panels, configurations, glint_reflectance, min_reflectance.
    """
    if not (0.0 <= float(min_reflectance) < 1.0) or not math.isfinite(min_reflectance):
        raise ValueError(f"min_reflectance must lie in [0, 1), got {min_reflectance}")
    cands = load_candidates(model_paths)
    features = cands[0].features
    cands.append(static_candidate())
    rows = _Rows(data_dir, features)
    test_R, test_pts = _earthlib_test()
    judged = [_Judged(c, rows, test_R, test_pts, float(min_reflectance)) for c in cands]
    models = [_model_entry(c, j, rows) for c, j in zip(cands, judged)]
    first, static = models[0], models[-1]
    out = {"models": models, "learned": first["overall"], "static": static["overall"],
           "sun_zenith_ge_60": {"learned": first["sun_zenith_ge_60"], "static": static["sun_zenith_ge_60"]},
           "bins": [{"sun_zenith_deg": a["sun_zenith_deg"], "camera_zenith_deg": a["camera_zenith_deg"],
                     "learned": {k: v for k, v in a.items() if not k.endswith("_deg")},
                     "static": {k: v for k, v in b.items() if not k.endswith("_deg")}}
                    for a, b in zip(first["bins"], static["bins"])],
           "features": features, "rows": rows.n, "rows_excluded_no_sunlit_panels": rows.excluded,
           "configurations": rows.n_cfg, "glint_reflectance": GLINT_REFLECTANCE,
           "render_revision": (manifest(data_dir) or {}).get("render_revision"),
           "backlit_min_relative_azimuth_deg": BACKLIT_MIN_DEG,
           "min_reflectance": float(min_reflectance)}
    if cands[0].boxes is not None:
        out["roc"] = _roc(cands[0], cands[-1], rows, test_pts, scales, float(min_reflectance))
    return out


def calibrate_to_budget(model_path: str | os.PathLike, data_dir: str | os.PathLike, out_path: str | os.PathLike,
                        scene_budget: float = 1e-4, pfa_budget: float = 1e-3,
                        min_reflectance: float = MIN_REFLECTANCE, iters: int = 30) -> dict:
    """Calibrate a checkpoint to the false-alarm budgets on a validation dataset (the held-out set): one scalar,
    the largest box scale (box models: ``BoxModel.scale``, every box shrunk about its centre) or the lowest
    logit threshold (classifiers), at which the share of the dataset's non-skin pixels called skin (under the
    brightness floor, as ``evaluate`` judges it) is within ``scene_budget`` and the earthlib test spectra within
    ``pfa_budget`` in every configuration of the dataset; never looser than the checkpoint's own tuning. Writes
    the calibrated checkpoint to ``out_path`` (its metadata records the calibration) and returns the record.

    Training holds the scene budget on the training dataset's own pixels; this holds it on pixels of other
    confusers and clothing (the test partition), where configuration-dependent boxes, shaped around what
    training showed them, let more through. The comparison and the choice then happen at the same budgets,
    and the fresh test set stays untouched."""
    if not (0.0 <= scene_budget < 1.0) or not (0.0 <= pfa_budget < 1.0):
        raise ValueError(f"budgets must lie in [0, 1), got scene {scene_budget}, earthlib {pfa_budget}")
    model, ck = load_model(model_path)
    calibrate = getattr(model, "calibrate_to_budget", None)
    if calibrate is None:
        raise ValueError(f"{str(model_path)!r}: detector kind {registry.kind_of(model)!r} cannot be calibrated")
    rows = _Rows(data_dir, list(model.features))
    test_R, test_pts = _earthlib_test()
    tb = test_R.mean(-1) > min_reflectance
    data = CalibrationData(R=rows.R, X=rows.X, ndgri=rows.g, ndsi=rows.s, ndvn=rows.v, cfg_X=rows.cfg_X,
                           nonskin=~rows.label, bright=rows.R.mean(-1) > min_reflectance, test_R=test_R,
                           test_bright=tb, test_pts=torch.where(tb[:, None], test_pts,
                                                                torch.full_like(test_pts, math.nan)))
    c = calibrate(data, scene_budget, pfa_budget, iters)
    knob, start, value, rate = c["knob"], c["before"], c["after"], c["pfa_scene"]
    record = {"data": str(data_dir), "scene_budget": scene_budget, "pfa_budget": pfa_budget, "knob": knob,
              "before": start, "after": value, "pfa_scene": rate, "rows": rows.n}
    registry.save(model, out_path, {**ck.get("meta", {}), "calibration": record})
    return record


def load_candidates(model_paths: ModelPaths) -> list[Candidate]:
    """The candidates of one path or a list of paths (``load_candidate``), which must take the same features."""
    paths = [model_paths] if isinstance(model_paths, (str, bytes)) or not hasattr(model_paths, "__iter__") \
        else list(cast(Sequence, model_paths))
    if not paths:
        raise ValueError("evaluate needs at least one model")
    cands = [load_candidate(p) for p in paths]
    features = cands[0].features
    for c in cands[1:]:
        if c.features != features:
            raise ValueError(f"models take different features: {c.name} {c.features} vs {cands[0].name} {features}")
    return cands


def _earthlib_test() -> tuple[torch.Tensor, torch.Tensor]:
    """The earthlib test spectra in the index bands: reflectance (m, 4) float32 and, row for row, their
    (NDGRI, NDSI, NDVN) (m, 3) (NaN: undefined)."""
    from .confusers import band_reflectance

    _, test_R = band_reflectance(INDEX_BANDS_NM, "test")
    test_R = test_R.float()
    return test_R, torch.stack(ratio_indices(test_R), -1)


def _bins(judged: _Judged, rows: _Rows) -> list[dict]:
    """``_Judged.summary`` per (sun zenith x camera zenith) bin that holds skin pixels."""
    bins = []
    for i in range(len(SUN_BINS) - 1):
        for k in range(len(CAMERA_BINS) - 1):
            m = (rows.sz >= SUN_BINS[i]) & (rows.sz < SUN_BINS[i + 1]) & (rows.cz >= CAMERA_BINS[k]) & \
                (rows.cz < CAMERA_BINS[k + 1])
            if bool((m & rows.label).any()):
                bins.append({"sun_zenith_deg": [SUN_BINS[i], SUN_BINS[i + 1]],
                             "camera_zenith_deg": [CAMERA_BINS[k], CAMERA_BINS[k + 1]], **judged.summary(rows, m)})
    return bins


#: relative-azimuth bins of ``evaluate`` (0: the sun behind the camera; >= ``BACKLIT_MIN_DEG``: back-lit)
AZIMUTH_BINS = (0.0, 60.0, 120.0, 180.01)


def _azimuth_bins(judged: _Judged, rows: _Rows) -> list[dict]:
    """``_Judged.summary`` per relative-azimuth bin (``AZIMUTH_BINS``)."""
    out = []
    for lo, hi in zip(AZIMUTH_BINS[:-1], AZIMUTH_BINS[1:]):
        m = (rows.ra >= lo) & (rows.ra < hi)
        if bool((m & rows.label).any()):
            out.append({"relative_azimuth_deg": [lo, min(hi, 180.0)], **judged.summary(rows, m)})
    return out


def _model_entry(cand: Candidate, judged: _Judged, rows: _Rows) -> dict:
    """One model's entry of ``evaluate``'s ``models``: overall, sun zenith >= 60°, per bin (sun x camera zenith,
    and relative azimuth), areas, scene Pfa by family."""
    area = judged.area_cfg
    return {"name": cand.name, "path": cand.path, "kind": cand.kind, "overall": judged.summary(rows),
            "sun_zenith_ge_60": judged.summary(rows, rows.sz >= 60), "bins": _bins(judged, rows),
            "azimuth_bins": _azimuth_bins(judged, rows),
            "area": {"mean": float(area.mean()), "median": float(area.median()),
                     "p10": float(area.quantile(0.1)), "p90": float(area.quantile(0.9))},
            "scene_pfa_by_family": judged.scene_by_family(rows)}


def _scaled(b: torch.Tensor, k: float) -> torch.Tensor:
    """Boxes (N, 4+) scaled by ``k`` about their centres in (NDGRI, NDSI) (a fifth column, d1, is kept)."""
    ctr = torch.stack([(b[:, 0] + b[:, 1]) / 2] * 2 + [(b[:, 2] + b[:, 3]) / 2] * 2, -1)
    return torch.cat([ctr + float(k) * (b[:, :4] - ctr), b[:, 4:]], -1)


def _roc(cand: Candidate, static: Candidate, rows: _Rows, test_pts, scales, floor: float) -> dict:
    """Pd (sunlit) against Pfa as every box is scaled about its centre, for ``cand`` and the static box."""
    out: dict[str, list] = {"scales": [float(k) for k in scales]}
    lit = rows.label & ~rows.shadow
    nonskin = ~rows.label
    for key, c in (("learned", cand), ("static", static)):
        boxes_of = cast(Callable, c.boxes)  # both are box models
        bx = boxes_of(rows.X)
        cb = boxes_of(rows.cfg_X)
        pts = []
        for k in scales:
            hit = inside_box(_scaled(bx, k), rows.g, rows.s, rows.v) & (rows.R.mean(-1) > floor)
            pts.append([float(false_alarm_rate(_scaled(cb, k), test_pts).mean()), _rate(hit, lit),
                        _rate(hit, nonskin)])
        out[key] = pts
    return out


def thesis_frame(detector_path: str | os.PathLike, size: int = 160, sun_zenith_deg: float = 45.0,
                 sun_azimuth_deg: float = 20.0, min_reflectance: float = 0.005,
                 plot: str | os.PathLike | None = None) -> dict:
    """The shipped detector on the thesis geometry, end to end: ``render``'s default scene (horizontal camera at
    9.449 m, Type I/II subject between a 0.97 and a 0.03 panel, sensor noise on) at ``size`` x ``size`` under
    the given sun, its signal frame calibrated by the onboard ELM through the panels' pixel regions, then
    ``detector.onnx`` through the onboard runtime (negative noise clipped, brightness floor). Returns the
    sunlit-skin detection of the learned boundaries and of the static box, the learned false alarms and the
    largest difference between the onboard and the renderer's ELM reflectance. ``plot``: a PNG of the 1080 nm
    reflectance beside both masks."""
    from .angles import relative_azimuth_deg
    from .onboard import OnboardDetector, elm_apply, elm_fit
    from .render.elm import panel_regions
    from .render.materials import compile_materials
    from .render.pipeline import render
    from .render.scene import Camera, Sun, default_scene
    from .render.sensor import Sensor

    sc = default_scene(camera=Camera(width=size, height=size),
                       sun=Sun(zenith_deg=sun_zenith_deg, azimuth_deg=sun_azimuth_deg, sky_fraction=0.1))
    res = render(sc, sensor=Sensor())
    signal = res.signal[0, 0].permute(2, 0, 1).cpu().numpy()
    regions = panel_regions(res.panel_pixels, list(sc.panels), size, size)
    reference = compile_materials(sc.materials, sc.bands, sc.suns, dtype=torch.float64).reference  # (M, B) DHR
    refs = {p: reference[list(sc.materials).index(sc.mesh(p).material)].tolist() for p in sc.panels}
    fit = elm_fit(signal, [(regions[p], refs[p]) for p in sc.panels])
    cube = elm_apply(signal, fit["gain"], fit["offset"])[None]
    rel = relative_azimuth_deg(sun_azimuth_deg, sc.cameras[0].azimuth_deg)
    out = OnboardDetector(detector_path)(cube, [[sun_zenith_deg, sc.cameras[0].zenith_deg, rel]], negative="clip",
                                  min_reflectance=min_reflectance)
    skin, lit = res.skin[0].cpu().numpy(), res.lit[0, 0].cpu().numpy()
    sunlit = skin & lit
    learned, static = out["mask"][0], res.mask[0, 0].cpu().numpy()
    n = max(int(sunlit.sum()), 1)
    if plot is not None:
        from .plots import mask_comparison

        rate = lambda m: f"{(m & sunlit).sum() / n:.2f} of sunlit skin, {int((m & ~skin).sum())} false alarms"  # noqa: E731
        mask_comparison(plot, cube[0, 2], {f"static box (thesis)\n{rate(static)}": static,
                                            f"learned boundaries (detector.onnx)\n{rate(learned)}": learned}, skin,
                        f"1080 nm reflectance (onboard ELM)\nsun zenith {sun_zenith_deg:g}°, camera horizontal")
    return {"sunlit_skin_pixels": int(sunlit.sum()), "pd_sunlit_learned": float((learned & sunlit).sum() / n),
            "pd_sunlit_static": float((static & sunlit).sum() / n), "false_alarms_learned": int((learned & ~skin).sum()),
            "out_of_domain": bool(out["out_of_domain"].any()),
            "elm_max_diff": float(np.abs(cube[0] - res.reflectance[0, 0].permute(2, 0, 1).cpu().numpy()).max())}


def boxes_plot(data_dir: str | os.PathLike, model_path: str | os.PathLike, path: str | os.PathLike,
               configs: Sequence[tuple[float, ...]] = ((15.0, 60.0, 30.0), (60.0, 60.0, 30.0), (80.0, 60.0, 30.0),
                                                       (80.0, 60.0, 160.0)),
               max_points: int = 20000) -> None:
    """How the boxes move with the configuration. Left: held-out skin pixels on (NDGRI, NDSI) (sunlit, colour:
    sun zenith; shadowed, grey), the earthlib test spectra, the static box and the learned box at a few
    configurations. Right: the learned edges (b1, b2, c1, c2 and the NDVN rule d1) against the sun zenith, camera
    zenith 60°, sun behind the camera (relative azimuth 0°), across (90°) and ahead of it (180°, back-lit)."""
    from matplotlib.patches import Rectangle

    from .plots import pyplot, save_figure

    features, boxes_of = box_function(model_path)
    rows = read_rows(data_dir, ["ndgri", "ndsi", "label", "shadow", "sun_zenith_deg"])
    label, shadow = rows["label"], rows["shadow"]
    rng = np.random.default_rng(0)

    def pick(m):
        cols = [rows[c][m] for c in ("ndgri", "ndsi", "sun_zenith_deg")]
        if len(cols[0]) > max_points:
            k = rng.choice(len(cols[0]), max_points, replace=False)
            cols = [c[k] for c in cols]
        return cols

    g, s, sz = pick(label & ~shadow)
    gs, ss, _ = pick(label & shadow)
    conf = confuser_indices("test").numpy()
    plt = pyplot()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13.0, 5.4), layout="constrained", width_ratios=[1.15, 1.0])
    ax.scatter(gs, ss, s=2, alpha=0.25, c="0.6", rasterized=True, label="shadowed skin")
    sc = ax.scatter(g, s, c=sz, s=2, alpha=0.35, cmap="viridis", vmin=0, vmax=90, rasterized=True)
    ax.scatter(conf[:, 0], conf[:, 1], s=5, c="k", marker="x", lw=0.6, label="earthlib test spectra")
    b = DEFAULT_BOX
    ax.add_patch(Rectangle((b.b1, b.c1), b.b2 - b.b1, b.c2 - b.c1, fill=False, ec="r", lw=1.8, label="static box (thesis)"))
    if len(features) == 3:
        boxes = boxes_of(np.array(configs, dtype=np.float32)).numpy()
        for k, (c, bx) in enumerate(zip(configs, boxes)):
            d1 = f", NDVN ≥ {bx[4]:.2f}" if len(bx) > 4 and bx[4] > -1 else ""
            ax.add_patch(Rectangle((bx[0], bx[2]), bx[1] - bx[0], bx[3] - bx[2], fill=False, ec=f"C{k + 1}", lw=1.4,
                                   ls=("-", "--", ":", "-.")[k % 4],
                                   label=f"learned: sun {c[0]:g}°, camera {c[1]:g}°, rel. az. {c[2]:g}°{d1}"))
        sun = np.linspace(0.0, 89.0, 90, dtype=np.float32)
        for ra, ls in ((0.0, "-"), (90.0, "--"), (180.0, ":")):
            bx = boxes_of(np.stack([sun, np.full_like(sun, 60.0), np.full_like(sun, ra)], -1)).numpy()
            for j, name in enumerate(("b1 NDGRI min", "b2 NDGRI max", "c1 NDSI min", "c2 NDSI max", "d1 NDVN min")):
                if j < bx.shape[1]:
                    ax2.plot(sun, bx[:, j], color=f"C{j}", ls=ls, lw=1.4, label=name if ra == 0.0 else None)
        for ra, ls in ((0.0, "-"), (90.0, "--"), (180.0, ":")):
            ax2.plot([], [], color="k", ls=ls, label=f"relative azimuth {ra:g}°")
        ax2.set_xlabel("sun zenith (deg), camera zenith 60°")
        ax2.set_ylabel("box edge (index units)")
        ax2.set_title("learned edges against the configuration")
        ax2.legend(fontsize=7, ncol=2, loc="best")
        ax2.grid(alpha=0.3)
    ax.set_xlim(-1.0, 0.6)
    ax.set_ylim(-0.2, 1.1)
    ax.set_xlabel("NDGRI (544, 633 nm)")
    ax.set_ylabel("NDSI (1080, 1580 nm)")
    ax.set_title("held-out skin (sunlit: colour = sun zenith; shadowed: grey) and confusers")
    cb = fig.colorbar(sc, ax=ax, fraction=0.04, label="sun zenith (deg)")
    cb.solids.set_alpha(1.0)  # the key at full colour, not at the points' transparency
    ax.legend(fontsize=6.5, loc="lower left")
    save_figure(fig, path)


def plots(result: dict, out_dir: str | os.PathLike) -> None:
    """The ROC (``roc.png``) and the Pd heat map per (sun zenith x camera zenith) bin (``pd_heatmap.png``) of an
    ``evaluate`` result, in ``out_dir``."""
    from pathlib import Path

    from .plots import pyplot, save_figure

    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    first = result["models"][0]["name"] if result.get("models") else "learned"
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    for name in ("learned", "static") if "roc" in result else ():
        pts = np.array(result["roc"][name], dtype=float)
        ax.plot(np.maximum(pts[:, 2], 1e-5), pts[:, 1], "o-", ms=3, label=f"{name} (scene non-skin pixels)")
        ax.plot(np.maximum(pts[:, 0], 1e-5), pts[:, 1], "s--", ms=3, label=f"{name} (earthlib test spectra)")
    ax.set_xscale("log")
    ax.set_xlabel("false-alarm probability (0 drawn at 1e-5)")
    ax.set_ylabel("Pd, sunlit skin")
    ax.grid(alpha=0.3, which="both")
    if "roc" in result:
        ax.legend(fontsize=7)
    ax.set_title(f"ROC: boxes scaled about their centres\n(learned: {first})" if "roc" in result
                 else "ROC: the first model has no boxes to scale", fontsize=9)
    fig.tight_layout()
    save_figure(fig, out / "roc.png")
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.4), layout="constrained")
    for ax, name in zip(axes, ("learned", "static")):
        grid = np.full((len(SUN_BINS) - 1, len(CAMERA_BINS) - 1), np.nan)
        for b in result["bins"]:
            i = SUN_BINS.index(b["sun_zenith_deg"][0])
            j = CAMERA_BINS.index(b["camera_zenith_deg"][0])
            grid[i, j] = b[name]["pd_sunlit"]
        im = ax.imshow(grid, vmin=0, vmax=1, cmap="viridis", origin="lower")
        ax.set_xticks(range(len(CAMERA_BINS) - 1), [f"{a:g}-{b:g}" for a, b in zip(CAMERA_BINS, CAMERA_BINS[1:])])
        ax.set_yticks(range(len(SUN_BINS) - 1), [f"{a:g}-{b:g}" for a, b in zip(SUN_BINS, SUN_BINS[1:])])
        ax.set_xlabel("camera zenith (deg)")
        ax.set_ylabel("sun zenith (deg)")
        ax.set_title(f"Pd sunlit skin, {name}" + (f" ({first})" if name == "learned" else " box (thesis)"),
                     fontsize=10)
        for (i, j), v in np.ndenumerate(grid):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", color="k" if v > 0.6 else "w", fontsize=7)
    fig.colorbar(im, ax=axes, fraction=0.03, label="Pd, sunlit skin (fraction detected)")
    save_figure(fig, out / "pd_heatmap.png")


__all__ = ["FEATURES", "evaluate", "plots"]


_TABLE = (("Pd sunlit", "pd_sunlit"), ("no glint", "pd_sunlit_no_glint"), ("glint", "pd_glint"),
          ("shadow", "pd_shadow"), ("backlit", "pd_backlit"), ("mean/config", "pd_sunlit_mean_over_configs"))


def table(result: dict) -> str:
    """The comparison as a text table: one row per model (the static box last)."""
    head = (f"{'model':<26}" + "".join(f"{h:>12}" for h, _ in _TABLE) + f"{'sun>=60 m/c':>12}{'Pfa earthlib':>13}"
            f"{'Pfa scene':>11}{'area':>7}")
    lines = [head]
    for m in result["models"]:
        o, hi = m["overall"], m["sun_zenith_ge_60"]
        lines.append(f"{m['name'][:25]:<26}" + "".join(f"{o[k]:>12.3f}" for _, k in _TABLE)
                     + f"{hi['pd_sunlit_mean_over_configs']:>12.3f}{o['pfa']:>13.2e}{o['pfa_scene']:>11.2e}"
                     + f"{m['area']['mean']:>7.3f}")
    lines.append(f"({result['rows']} rows, {result['configurations']} configurations; Pd sunlit split into glint-"
                 f"affected (specular >= {result['glint_reflectance']:g} at 1580 nm) and not; shadow: skin without "
                 f"direct sun; backlit: all skin of configurations with relative azimuth >= {BACKLIT_MIN_DEG:g}° (the "
                 "camera looks towards the sun); area: mean decision-region area per configuration in the (NDGRI, "
                 "NDSI) plane)")
    return "\n".join(lines)


def compare_plot(result: dict, path: str | os.PathLike) -> None:
    """Bars per model: Pd (sunlit without glint, glint-affected, shadowed, back-lit, sun >= 60° mean over
    configurations), false alarms (earthlib test and scene non-skin, log scale) and the decision-region area."""
    from .plots import pyplot, save_figure

    plt = pyplot()
    models = result["models"]
    names = [m["name"] for m in models]
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 4.2), gridspec_kw={"width_ratios": [2.2, 1.2, 1]})
    cats = [("sunlit, no glint", lambda m: m["overall"]["pd_sunlit_no_glint"]),
            ("glint-affected", lambda m: m["overall"]["pd_glint"]),
            ("shadowed", lambda m: m["overall"]["pd_shadow"]),
            ("back-lit (all skin)", lambda m: m["overall"]["pd_backlit"]),
            ("sun ≥ 60°, mean/config", lambda m: m["sun_zenith_ge_60"]["pd_sunlit_mean_over_configs"])]
    x = np.arange(len(cats))
    w = 0.8 / len(models)
    for k, m in enumerate(models):
        a1.bar(x + (k - (len(models) - 1) / 2) * w, [f(m) for _, f in cats], w, label=names[k])
    a1.set_xticks(x, [c for c, _ in cats], fontsize=8)
    a1.set_ylabel("Pd (held-out skin pixels)")
    a1.set_ylim(0, 1.3)
    a1.set_yticks(np.linspace(0, 1, 6))
    a1.grid(alpha=0.3, axis="y")
    a1.legend(fontsize=7, loc="upper center", ncol=min(4, len(models)))
    x2 = np.arange(2)
    for k, m in enumerate(models):
        a2.bar(x2 + (k - (len(models) - 1) / 2) * w, [max(m["overall"]["pfa"], 1e-6), max(m["overall"]["pfa_scene"], 1e-6)],
               w)
    a2.set_yscale("log")
    a2.set_ylim(5e-7, 1)
    a2.set_xticks(x2, ["earthlib test", "scene non-skin"], fontsize=8)
    a2.set_ylabel("Pfa (0 drawn at 1e-6)")
    a2.grid(alpha=0.3, axis="y", which="both")
    a3.bar(np.arange(len(models)), [m["area"]["mean"] for m in models], color=[f"C{k}" for k in range(len(models))])
    a3.set_xticks(np.arange(len(models)), names, fontsize=7, rotation=25, ha="right")
    a3.set_ylabel("decision-region area, (NDGRI, NDSI) units²")
    a3.grid(alpha=0.3, axis="y")
    fig.suptitle(f"Held-out comparison ({result['configurations']} configurations)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


#: the model kinds whose detector graph meets the onboard budget (a 1 MP frame in a few times the time of reading
#: it): the box models' five edge forms (~4 ms per 1024² frame on 2 cores). The classifier's per-pixel MLP (3 ->
#: 32 -> 32 -> 1) takes ~170 ms per frame, 40x more: it is evaluated and reported, not shipped as detector.onnx
ONBOARD_KINDS = ("boxes",)


def select_detector(result: dict, pfa_budget: float = 1e-3, scene_budget: float = 1e-4,
                    tolerance: float = 0.005, onboard_kinds: tuple[str, ...] = ONBOARD_KINDS) -> tuple[str, str]:
    """The model to ship as ``detector.onnx``: among the evaluated models (not the static box) of a kind that meets
    the onboard budget (``onboard_kinds``; any model when none does) whose held-out Pfa is within ``pfa_budget``
    on the earthlib test spectra and ``scene_budget`` on scene non-skin pixels, those within ``tolerance`` of
    the highest sunlit Pd; of these a box model (auditable rules, the cheaper graph) before a classifier, then
    the smallest mean decision-region area (at equal Pd, less false-alarm exposure than earthlib can show).
    Returns (model name, the reason in words; it names the models left out for their onboard cost)."""
    every = [m for m in result["models"] if m["kind"] != "static"]
    if not every:
        raise ValueError("no model to choose from")
    models = [m for m in every if m["kind"] in onboard_kinds] or every
    costly = [m for m in every if m not in models]

    def ok(m):
        return m["overall"]["pfa"] <= pfa_budget and m["overall"]["pfa_scene"] <= scene_budget

    eligible = [m for m in models if ok(m)] or models
    best = max(m["overall"]["pd_sunlit"] for m in eligible)
    near = [m for m in eligible if m["overall"]["pd_sunlit"] >= best - tolerance]
    pick = min(near, key=lambda m: (m["kind"] != "boxes", m["area"]["mean"]))
    figures = "; ".join(f"{m['name']}: Pd sunlit {m['overall']['pd_sunlit']:.3f}, Pfa earthlib "
                        f"{m['overall']['pfa']:.1e}, scene {m['overall']['pfa_scene']:.1e}, mean area "
                        f"{m['area']['mean']:.3f}" for m in every)
    why = (f"within {tolerance:g} of the highest held-out sunlit Pd among the models inside the false-alarm budgets "
           f"(earthlib test <= {pfa_budget:g}, scene non-skin <= {scene_budget:g}), a box model first, then the "
           "smallest decision region" if ok(pick) else
           "no model met the false-alarm budgets on the held-out set; highest sunlit Pd")
    if costly:
        why += ("; not eligible for their onboard cost (a per-pixel MLP, ~40x the box graph's time per frame): "
                + ", ".join(m["name"] for m in costly))
    return pick["name"], f"{why}. Held-out ({result.get('data', '')}): {figures}."
