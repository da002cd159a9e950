"""Detection metrics over dataset rows, for any decision: a boolean array per row (whatever features made it)
judged against the rows' labels, shadow, configuration groups and material families. Pd (skin pixels called
skin) and Pfa (non-skin pixels called skin), overall, per category and per (sun zenith x camera zenith) or
relative-azimuth bin; nothing here depends on the (NDGRI, NDSI) plane (``evaluation.regions`` holds what does).

>>> import numpy as np
>>> rates(np.array([True, False, True, False]), np.array([True, True, False, False]))
{'pd': 0.5, 'pfa': 0.5, 'skin_pixels': 2, 'nonskin_pixels': 2}
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import ArrayLike

from ..angles import BACKLIT_MIN_DEG
from ..bands import INDEX_BANDS_NM
from ..dataset.files import dataset_bands, read_rows
from ..dataset.schema import Rows, has_band
from ..detectors.features import BAND_COLUMNS, feature_columns, stack_features
from ..detectors.features import MIN_REFLECTANCE as _MIN_REFLECTANCE

SUN_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
CAMERA_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
#: relative-azimuth bins of ``evaluate`` (0: the sun behind the camera; >= ``BACKLIT_MIN_DEG``: back-lit)
AZIMUTH_BINS = (0.0, 60.0, 120.0, 180.01)
#: a sunlit skin pixel is glint-affected when the specular lobe adds at least this much apparent reflectance
#: (π f_s) at 1580 nm (section 3.3.3 parameters): enough to move NDSI by about 0.02 or more
GLINT_REFLECTANCE = 0.01
#: brightness floor of the evaluation protocol, applied to every model alike (``detectors.features.MIN_REFLECTANCE``)
MIN_REFLECTANCE = _MIN_REFLECTANCE


def rate(hit: torch.Tensor, m: torch.Tensor) -> float:
    """The share of the rows ``m`` selects where ``hit`` is true (NaN when it selects none)."""
    return float(hit[m].float().mean()) if bool(m.any()) else float("nan")


def mean_over_groups(values: torch.Tensor, group: torch.Tensor, n_groups: int) -> float:
    """Mean over groups (ids in [0, ``n_groups``)) of the per-group mean of ``values`` (rows of ``group``); NaN
    without rows."""
    if values.numel() == 0:
        return float("nan")
    s = torch.zeros(n_groups, dtype=torch.float64).index_add_(0, group, values.double())
    c = torch.zeros(n_groups, dtype=torch.float64).index_add_(0, group, torch.ones_like(values, dtype=torch.float64))
    return float((s[c > 0] / c[c > 0]).mean())


def rates(decision: ArrayLike, label: ArrayLike, mask: ArrayLike | None = None) -> dict:
    """Pd and Pfa of any per-row decision (bool (n,)) against the rows' labels (bool (n,), True: skin), over the
    rows ``mask`` selects (all by default): ``pd`` (skin rows called skin), ``pfa`` (non-skin rows called skin),
    ``skin_pixels``, ``nonskin_pixels``."""
    hit = torch.as_tensor(np.asarray(decision, dtype=bool))
    lab = torch.as_tensor(np.asarray(label, dtype=bool))
    m = torch.ones_like(lab) if mask is None else torch.as_tensor(np.asarray(mask, dtype=bool))
    return {"pd": rate(hit, lab & m), "pfa": rate(hit, ~lab & m), "skin_pixels": int((lab & m).sum()),
            "nonskin_pixels": int((~lab & m).sum())}


def row_rates(rows: Rows, decision: ArrayLike, mask: ArrayLike | None = None, group: str | None = None) -> dict:
    """``rates`` of a decision over typed rows (``dataset.files.read_rows``: its ``label`` column), and, with
    ``group`` (a column, e.g. "group"), ``pd_mean_over_groups``: the mean over that column's values of each
    one's Pd."""
    out = rates(decision, rows["label"], mask)
    if group is not None:
        lab = np.asarray(rows["label"], dtype=bool) & (True if mask is None else np.asarray(mask, dtype=bool))
        _, inverse = np.unique(rows[group], return_inverse=True)
        gid = torch.as_tensor(inverse.reshape(-1).astype(np.int64))
        hit = torch.as_tensor(np.asarray(decision, dtype=bool))
        sel = torch.as_tensor(lab)
        out["pd_mean_over_groups"] = mean_over_groups(hit[sel].float(), gid[sel], int(gid.max()) + 1 if len(gid) else 0)
    return out


def glint_affected(theta_i_deg: ArrayLike, theta_r_deg: ArrayLike, delta_phi_deg: ArrayLike) -> torch.Tensor:
    """Whether the specular lobe (eq 2.3.4, section 3.3.3 parameters at 1580 nm) adds at least
    ``GLINT_REFLECTANCE`` apparent reflectance π f_s at these local angles (degrees)."""
    from ..optics import THESIS_SPECULAR, microfacet_brdf

    d = math.pi / 180
    sig, rho0 = THESIS_SPECULAR.at(torch.tensor([1580.0], dtype=torch.float64))
    f = microfacet_brdf(torch.as_tensor(theta_i_deg, dtype=torch.float64) * d,
                        torch.as_tensor(theta_r_deg, dtype=torch.float64) * d,
                        torch.as_tensor(delta_phi_deg, dtype=torch.float64) * d, sig[0], rho0[0])
    return math.pi * f >= GLINT_REFLECTANCE


def families(col: dict) -> np.ndarray:
    """Per row, the family of what a non-skin pixel shows: "ground", "clothing: <earthlib class>",
    "confuser: <earthlib class>" (datasets written before the material column: confusers and "other")."""
    from ..confusers import family

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


class HeldOut:
    """The held-out rows a model is judged on (typed ``Rows`` of ``read_rows``), with their configurations and
    categories as tensors: features ``X``, reflectance ``R``, label, shadow, glint, angles, configuration id."""

    def __init__(self, rows: Rows, features, band_columns: Sequence[str] = BAND_COLUMNS):
        self.excluded = rows.excluded
        self.n = len(rows)
        col = rows.columns
        X = torch.from_numpy(stack_features(rows, features))
        self._feature = {f: X[:, j] for j, f in enumerate(features)}  # each feature read, for ``X_of``
        self.X = X
        self.R = torch.from_numpy(rows.stack(band_columns, np.float32))  # the models' bands, in their order
        self.g, self.s = torch.from_numpy(col["ndgri"]).float(), torch.from_numpy(col["ndsi"]).float()
        index = all(has_band(rows.band_set, w) for w in INDEX_BANDS_NM)
        self.v = (torch.from_numpy(rows.index("ndvn", np.float32)) if index  # float32, as ratio_indices(self.R)
                  else torch.full((self.n,), math.nan))  # the index plane exists with the index bands only
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
        self.family = families(col)
        self.features = list(features)

    def X_of(self, features: Sequence[str]) -> torch.Tensor:
        """The configuration (n, k) of ``features``, any of those the rows were read with (models that take
        different features are judged on the same rows)."""
        missing = [f for f in features if f not in self._feature]
        if missing:
            raise ValueError(f"the rows hold no feature {', '.join(missing)} (read: {', '.join(self.features)})")
        for f in features:
            if not bool(torch.isfinite(self._feature[f]).all()):
                raise ValueError(f"the dataset does not record {f} for every row (diffuse_share comes from sky_fraction, "
                                 "recorded at 544 nm: a dataset without a band there has none): a model taking it "
                                 "cannot be judged on it")
        if list(features) == self.features:
            return self.X
        return torch.stack([self._feature[f] for f in features], -1) if features else torch.zeros(self.n, 0)


def held_out(data_dir: str | os.PathLike, features, bands_nm: Sequence[float] = INDEX_BANDS_NM) -> HeldOut:
    """The ``HeldOut`` rows of a dataset folder for models taking ``features`` and reading the bands
    ``bands_nm`` (their columns in the dataset's own set, ``dataset_bands``: the caller checks it holds them)."""
    have = dataset_bands(data_dir)
    band_cols = [have.columns[have.index(w)] for w in bands_nm]
    cols = list(dict.fromkeys([*feature_columns(features), "sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg",
                               "label", "shadow", "ndgri", "ndsi", "group", "sun", "skin", *band_cols,
                               "theta_i_deg", "theta_r_deg", "delta_phi_deg"]))
    rows = read_rows(data_dir, cols, optional=("material", "confuser", "clothing"))  # checks the folder, columns
    if len(rows) == 0:
        raise ValueError(f"no rows with a valid ELM in {str(data_dir)!r}")
    return HeldOut(rows, features, band_cols)


@dataclass
class Judged:
    """One model's decisions on the rows (``hit``, bool (n,)), with its earthlib-test Pfa and decision-region area
    per configuration (``evaluation.regions.judge``)."""

    hit: torch.Tensor
    pfa_cfg: torch.Tensor
    area_cfg: torch.Tensor

    def summary(self, rows: HeldOut, m: torch.Tensor | None = None) -> dict:
        """Pd by skin category, Pfa and pixel counts over the rows ``m`` selects (all by default)."""
        m = torch.ones_like(rows.label) if m is None else m
        sk = rows.label & m
        lit = sk & ~rows.shadow
        cfgs = torch.unique(rows.cfg[m]) if bool(m.any()) else torch.zeros(0, dtype=torch.long)
        nonskin = ~rows.label & m
        hit = self.hit
        return {"pd": rate(hit, sk), "pd_sunlit": rate(hit, lit),
                "pd_sunlit_mean_over_configs": mean_over_groups(hit[lit].float(), rows.cfg[lit], rows.n_cfg),
                "pd_sunlit_no_glint": rate(hit, lit & ~rows.glint), "pd_glint": rate(hit, lit & rows.glint),
                "pd_shadow": rate(hit, sk & rows.shadow),
                "pd_backlit": rate(hit, sk & rows.backlit),
                "pd_backlit_sunlit": rate(hit, lit & rows.backlit),
                "pfa": float(self.pfa_cfg[cfgs].mean()) if cfgs.numel() else float("nan"),
                "pfa_scene": rate(hit, nonskin),
                "pfa_scene_sunlit": rate(hit, nonskin & ~rows.shadow),
                "pfa_scene_shadow": rate(hit, nonskin & rows.shadow),
                "area_mean": float(self.area_cfg[cfgs].mean()) if cfgs.numel() else float("nan"),
                "skin_pixels": int(sk.sum()), "sunlit_skin_pixels": int(lit.sum()),
                "shadow_skin_pixels": int((sk & rows.shadow).sum()), "backlit_skin_pixels": int((sk & rows.backlit).sum()),
                "nonskin_pixels": int(nonskin.sum()),
                "glint_pixels": int((lit & rows.glint).sum())}

    def scene_by_family(self, rows: HeldOut) -> dict:
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


def bins(judged: Judged, rows: HeldOut) -> list[dict]:
    """``Judged.summary`` per (sun zenith x camera zenith) bin that holds skin pixels."""
    out = []
    for i in range(len(SUN_BINS) - 1):
        for k in range(len(CAMERA_BINS) - 1):
            m = (rows.sz >= SUN_BINS[i]) & (rows.sz < SUN_BINS[i + 1]) & (rows.cz >= CAMERA_BINS[k]) & \
                (rows.cz < CAMERA_BINS[k + 1])
            if bool((m & rows.label).any()):
                out.append({"sun_zenith_deg": [SUN_BINS[i], SUN_BINS[i + 1]],
                            "camera_zenith_deg": [CAMERA_BINS[k], CAMERA_BINS[k + 1]], **judged.summary(rows, m)})
    return out


def azimuth_bins(judged: Judged, rows: HeldOut) -> list[dict]:
    """``Judged.summary`` per relative-azimuth bin (``AZIMUTH_BINS``)."""
    out = []
    for lo, hi in zip(AZIMUTH_BINS[:-1], AZIMUTH_BINS[1:]):
        m = (rows.ra >= lo) & (rows.ra < hi)
        if bool((m & rows.label).any()):
            out.append({"relative_azimuth_deg": [lo, min(hi, 180.0)], **judged.summary(rows, m)})
    return out


__all__ = ["AZIMUTH_BINS", "CAMERA_BINS", "GLINT_REFLECTANCE", "MIN_REFLECTANCE", "SUN_BINS", "HeldOut", "Judged",
           "azimuth_bins", "bins", "families", "glint_affected", "held_out", "mean_over_groups", "rate", "rates",
           "row_rates"]
