"""What every detector kind shares, without importing a learner: the dataset's band columns (``BAND_COLUMNS``,
whose home is ``torchskin.dataset.schema``, re-exported here), the configuration features (order, units, training
domain), the brightness floor, the index formulas (``ratio_indices``; its one home is ``torchskin.detect``,
re-exported here), the configuration inputs' standardisation and domain buffers (``config_buffers``), the
configurations a false-alarm budget is enforced on (``tuning_configs``) and the earthlib spectra in the index bands
(``earthlib_reflectance``, ``confuser_indices``).

This module imports no learner (``torchskin.detectors.boxes`` / ``classifier``). ``torchskin.dataset`` imports nothing
of ``torchskin.detectors``: the dataset's schema is ``torchskin.dataset.schema``, below the detectors.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
import torch

from ..bands import INDEX_BANDS_NM
from ..dataset.schema import BAND_COLUMNS
from ..detect import ratio_indices

#: default configuration features (what an onboard computer knows: sun position and camera pointing)
FEATURES = ("sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg")
#: the sky's share of the light on an open horizontal surface at 544 nm (the first band): diffuse horizontal over
#: global horizontal irradiance, in [0, 1]. A horizontal panel in the sun and one in shade measure it every frame
#: (E_shade / E_sun). Haze raises it: under it a shadow is lit by a bluer, relatively stronger sky
DIFFUSE_SHARE = "diffuse_share"
FEATURE_UNITS = {"sun_zenith_deg": "deg", "camera_zenith_deg": "deg", "relative_azimuth_deg": "deg",
                 "range_m": "m", DIFFUSE_SHARE: "1"}
#: training domain of each feature (inputs outside it are flagged onboard)
FEATURE_DOMAIN = {"sun_zenith_deg": (0.0, 90.0), "camera_zenith_deg": (0.0, 90.0),
                  "relative_azimuth_deg": (0.0, 180.0), "range_m": (0.0, 10000.0), DIFFUSE_SHARE: (0.0, 1.0)}


def diffuse_share(sky_fraction: Any, sun_zenith_deg: Any) -> np.ndarray:
    """The diffuse share of horizontal irradiance, D / (D + B cos(sun zenith)), from the dataset's ``sky_fraction``
    (D / B: diffuse horizontal over direct normal) and the sun zenith; 1 with the sun at or below the horizon, NaN
    where ``sky_fraction`` is (a dataset without a band at 544 nm does not record it). float32.

    >>> diffuse_share([0.1, 1.0, 0.3, float("nan")], [0.0, 60.0, 90.0, 30.0]).round(4)
    array([0.0909, 0.6667, 1.    ,    nan], dtype=float32)
    """
    s = np.asarray(sky_fraction, np.float64)
    c = np.cos(np.deg2rad(np.asarray(sun_zenith_deg, np.float64)))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(c > 1e-12, s / (s + c), np.where(np.isnan(s), np.nan, 1.0))
    return out.astype(np.float32)


#: features computed from dataset columns rather than stored: the columns each needs and the function of them
#: (``stack_features``)
DERIVED_FEATURES = {DIFFUSE_SHARE: (("sky_fraction", "sun_zenith_deg"), diffuse_share)}


def feature_columns(features: Sequence[str]) -> list[str]:
    """The dataset columns that give ``features`` (derived ones, ``DERIVED_FEATURES``, by their sources)."""
    cols: list[str] = []
    for f in features:
        cols += DERIVED_FEATURES[f][0] if f in DERIVED_FEATURES else (f,)
    return list(dict.fromkeys(cols))


def stack_features(rows: Any, features: Sequence[str], dtype: Any = np.float32) -> np.ndarray:
    """The configuration (N, k) of ``rows`` (``dataset.schema.Rows`` read with ``feature_columns``): one column per
    feature, derived ones computed (``diffuse_share``)."""
    cols = [DERIVED_FEATURES[f][1](*(rows[c] for c in DERIVED_FEATURES[f][0])) if f in DERIVED_FEATURES
            else np.asarray(rows[f]) for f in features]
    return (np.stack(cols, 1) if cols else np.zeros((len(rows), 0))).astype(dtype)
#: brightness floor of the evaluation protocol and of the onboard detector: a pixel whose mean reflectance over the
#: bands is not above it is not skin (at the noise floor its indices are ratios of sensor noise; the onboard runtime
#: applies the same floor, ``min_reflectance``, recorded in the exported detector's metadata)
MIN_REFLECTANCE = 0.005


def config_buffers(features: Sequence[str], mean: Any = None, std: Any = None,
                   domain: Any = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The configuration inputs' standardisation (mean, std: (k,), default 0 and 1) and training domain (k, 2;
    default ``FEATURE_DOMAIN``, unbounded for other features) that box models and classifiers keep as buffers."""
    k = len(features)
    if domain is None:
        domain = [FEATURE_DOMAIN.get(f, (-1e30, 1e30)) for f in features]
    return (torch.zeros(k) if mean is None else torch.as_tensor(mean, dtype=torch.float32),
            torch.ones(k) if std is None else torch.as_tensor(std, dtype=torch.float32),
            torch.as_tensor(domain, dtype=torch.float32).reshape(k, 2))


def distinct_configs(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of ``X`` (n, k) and, per row of ``X``, the index of its distinct row."""
    uniq, inv = np.unique(X.numpy(), axis=0, return_inverse=True)
    return torch.from_numpy(uniq), torch.from_numpy(inv.reshape(-1))


class HasDomain(Protocol):
    """Anything with a training domain per configuration feature: a (k, 2) tensor of (low, high)."""

    @property
    def domain(self) -> torch.Tensor: ...


def tuning_configs(model: HasDomain, X: torch.Tensor, grid: int = 10) -> torch.Tensor:
    """The configurations the false-alarm budget is enforced on: every distinct training configuration in
    ``X`` and a lattice of ``grid ** k`` points (k features) over the model's training domain."""
    uniq = distinct_configs(X)[0].float()
    axes = [torch.linspace(float(lo), float(hi), grid) for lo, hi in model.domain]
    lattice = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))
    return torch.cat([uniq, lattice])


def domain_from_manifest(data_dir: str | os.PathLike,
                         features: Sequence[str] = FEATURES) -> list[tuple[float, float]] | None:
    """The training domain of each feature as declared by the dataset's configuration (``_manifest.json``):
    the ranges the configurations were drawn from, not the extremes of the draws. None without a manifest."""
    from ..dataset.files import manifest

    man = manifest(data_dir)
    if man is None:
        return None
    cfg = man.get("config", {})
    declared = {"sun_zenith_deg": cfg.get("sun", {}).get("zenith_deg"),
                "camera_zenith_deg": cfg.get("camera", {}).get("zenith_deg"),
                "range_m": cfg.get("camera", {}).get("range_m"),
                "relative_azimuth_deg": [0.0, 180.0], DIFFUSE_SHARE: list(FEATURE_DOMAIN[DIFFUSE_SHARE])}
    out = []
    for f in features:
        r = declared.get(f)
        if r is None:
            return None
        out.append((float(r[0]), float(r[1])))
    return out


def earthlib_reflectance(part: str = "train", bands_nm: Sequence[float] = INDEX_BANDS_NM) -> torch.Tensor:
    """The earthlib spectra of one partition at the band centres ``bands_nm`` (default the four index bands,
    ``INDEX_BANDS_NM``; as ``generate`` samples its confusers), (m, n) float32."""
    from ..confusers import band_reflectance

    _, R = band_reflectance(list(bands_nm), part)
    return R.float()


def confuser_indices(part: str = "train") -> torch.Tensor:
    """(NDGRI, NDSI, NDVN) of the earthlib spectra of one partition, (n, 3): geometry-independent (Lambertian:
    a geometric factor scales every band alike). Spectra whose indices are undefined (zero reflectance in a
    band pair) are left out: no box holds them."""
    from ..confusers import band_reflectance

    _, R = band_reflectance(INDEX_BANDS_NM, part)
    pts = torch.stack(ratio_indices(R.float()), -1)
    return pts[torch.isfinite(pts).all(-1)]


__all__ = ["BAND_COLUMNS", "DERIVED_FEATURES", "DIFFUSE_SHARE", "FEATURES", "FEATURE_DOMAIN", "FEATURE_UNITS",
           "HasDomain", "MIN_REFLECTANCE", "config_buffers", "confuser_indices", "diffuse_share", "distinct_configs",
           "domain_from_manifest", "earthlib_reflectance", "feature_columns", "ratio_indices", "stack_features",
           "tuning_configs"]
