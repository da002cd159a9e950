"""Which bands, and how many, detect skin best at the false-alarm budget: a greedy forward search over bands
synthesised from a dataset rendered once at fine spectral sampling, each candidate set scored by a fast proxy
learner on held-out rows.

>>> sorted(RANGES)
['both', 'ingaas', 'silicon']

The proxy is the lookup-table kind's learner (LightGBM on the reflectances, every normalized difference, the log
brightness and the configuration: ``detectors.lut.train.learner_features``) with few trees and no table. Its
score is held-out Pd of sunlit skin at a scene false-alarm budget, the threshold set on the held-out non-skin
rows, as ``calibrate_to_budget`` sets a detector's. The search chooses among many sets on those rows, so the
chosen sets are then scored on a fresh dataset (``fresh_pd``: the threshold from the held-out rows, Pd and Pfa on
the fresh ones). A band is synthesised from the fine dataset's columns through the renderer's band response
(``onboard.band_plan``, ``bands.response_weights``), as a hyperspectral cube is read by ``detect``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..bands import Band

#: detector ranges (nm) of the search: silicon, InGaAs, and a camera with both
RANGES = {"silicon": (400.0, 1000.0), "ingaas": (900.0, 1700.0), "both": (400.0, 1700.0)}


@dataclass
class DesignRows:
    """Rows of the fine dataset: training and held-out reflectance at the fine centres (n, m), configuration
    (n, 3), skin label, held-out sunlit skin; optionally a fresh set's (``fresh_pd``)."""

    centres: list[float]
    R: np.ndarray
    X: np.ndarray
    y: np.ndarray
    R_val: np.ndarray
    X_val: np.ndarray
    y_val: np.ndarray
    lit_val: np.ndarray
    fresh: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None  # R, X, y, lit


def load_design_rows(train_dir: str | os.PathLike, heldout_dir: str | os.PathLike, max_rows: int = 200_000,
                     seed: int = 0, fresh_dir: str | os.PathLike | None = None) -> DesignRows:
    """The training, held-out (and fresh) rows (physical-ELM frames, above the brightness floor, at most
    ``max_rows`` each, a seeded draw) of datasets rendered in the same fine bands."""
    from pathlib import Path

    from ..dataset.files import dataset_bands, read_rows
    from ..detectors.features import FEATURES, MIN_REFLECTANCE

    for d in (train_dir, heldout_dir, fresh_dir):
        if d is not None and not (Path(d) / "_manifest.json").is_file():
            raise ValueError(f"dataset folder {str(d)!r} does not exist or holds no dataset (torchskin generate "
                             "writes one)")
    bands = dataset_bands(train_dir)
    for other in (heldout_dir, fresh_dir):
        if other is not None and dataset_bands(other) != bands:
            raise ValueError(f"datasets {str(train_dir)!r} and {str(other)!r} hold different bands")
    if len(bands) < 8:
        raise ValueError(f"dataset {str(train_dir)!r} holds {len(bands)} bands; the band design synthesises bands "
                         "from a fine spectral sampling (e.g. generate --bands 400:1700:10)")
    cols = list(bands.columns)
    rng = np.random.default_rng(seed)

    def rows(d):
        r = read_rows(d, [*FEATURES, *cols, "label", "shadow"])
        R = r.stack(cols, np.float64)
        keep = np.flatnonzero(np.isfinite(R).all(1) & (R.mean(1) > MIN_REFLECTANCE))
        if len(keep) > max_rows:
            keep = np.sort(rng.choice(keep, max_rows, replace=False))
        y = r["label"].astype(bool)[keep]
        return R[keep], r.stack(FEATURES, np.float64)[keep], y, y & ~r["shadow"].astype(bool)[keep]

    R, X, y, _ = rows(train_dir)
    Rv, Xv, yv, lv = rows(heldout_dir)
    return DesignRows(list(bands.centers), R, X, y, Rv, Xv, yv, lv, rows(fresh_dir) if fresh_dir else None)


def synthesis(centres: Sequence[float], bands: Sequence[Band]) -> np.ndarray:
    """(k, m) weights that give ``bands`` from reflectance sampled at ``centres`` (``onboard.band_plan``)."""
    from ..onboard import band_plan

    plan = band_plan(list(centres), None, list(bands))
    if plan["kind"] == "reorder":
        m = np.zeros((len(bands), len(centres)))
        m[np.arange(len(bands)), plan["order"]] = 1.0
        return m
    return plan["matrix"]


def _proxy(rows: DesignRows, bands: Sequence[Band], trees: int, budget: float, seed: int):
    """The proxy trained on ``bands``, its scorer and its threshold at ``budget`` on the held-out non-skin rows."""
    import lightgbm as lgb

    from ..detectors.lut.train import LEARNER, learner_features

    W = synthesis(rows.centres, bands).T
    booster = lgb.train({**LEARNER, "seed": int(seed)}, lgb.Dataset(learner_features(rows.R @ W, rows.X),
                                                                    rows.y.astype(np.float64)),
                        num_boost_round=int(trees))

    def score(R, X):
        return booster.predict(learner_features(R @ W, X), raw_score=True, num_threads=1)

    s = score(rows.R_val, rows.X_val)
    neg = np.sort(s[~rows.y_val])[::-1]
    allowed = int(np.floor(budget * len(neg)))  # non-skin rows allowed above the threshold
    return score, s, (neg[allowed] if allowed < len(neg) else -np.inf)


def proxy_pd(rows: DesignRows, bands: Sequence[Band], trees: int = 40, budget: float = 1e-4,
             seed: int = 0) -> dict:
    """Held-out Pd of sunlit skin of the proxy learner on ``bands`` at the scene false-alarm ``budget`` (the
    threshold set on the held-out non-skin rows), and the held-out Pfa it reaches."""
    _, s, thr = _proxy(rows, bands, trees, budget, seed)
    return {"bands": [[b.center_nm, b.fwhm_nm] for b in bands], "pd_sunlit": float((s[rows.lit_val] > thr).mean()),
            "pfa_scene": float((s[~rows.y_val] > thr).mean()), "threshold": float(thr)}


def fresh_pd(rows: DesignRows, bands: Sequence[Band], trees: int = 40, budget: float = 1e-4,
             seed: int = 0) -> dict:
    """``proxy_pd`` and, on the fresh rows (``load_design_rows(fresh_dir=...)``), Pd of sunlit skin and the scene
    Pfa at the held-out threshold: how a chosen set does where nothing was chosen."""
    if rows.fresh is None:
        raise ValueError("fresh_pd needs the fresh rows (load_design_rows(..., fresh_dir=...))")
    score, s, thr = _proxy(rows, bands, trees, budget, seed)
    R, X, y, lit = rows.fresh
    f = score(R, X)
    return {"bands": [[b.center_nm, b.fwhm_nm] for b in bands], "pd_sunlit": float((s[rows.lit_val] > thr).mean()),
            "pfa_scene": float((s[~rows.y_val] > thr).mean()), "threshold": float(thr),
            "fresh_pd_sunlit": float((f[lit] > thr).mean()), "fresh_pfa_scene": float((f[~y] > thr).mean())}


def greedy(rows: DesignRows, candidates: Sequence[Band], k_max: int, trees: int = 40, budget: float = 1e-4,
           progress=None) -> list[dict]:
    """Greedy forward selection: for k = 1 ... ``k_max``, the candidate band that, added to the best set of k - 1,
    scores the highest ``proxy_pd``; one entry per k (its bands in ascending order, its score)."""
    chosen: list[Band] = []
    out = []
    for _k in range(k_max):
        best = None
        for c in candidates:
            if c in chosen:
                continue
            trial = sorted([*chosen, c], key=lambda b: b.center_nm)
            r = proxy_pd(rows, trial, trees, budget)
            if best is None or r["pd_sunlit"] > best[1]["pd_sunlit"]:
                best = (c, r)
            if progress is not None:
                progress()
        assert best is not None
        chosen.append(best[0])
        out.append({"k": len(chosen), **best[1]})
    return out


def candidates(range_nm: tuple[float, float], step_nm: float, fwhm_nm: float,
               within: tuple[float, float]) -> list[Band]:
    """Bands every ``step_nm`` of ``fwhm_nm`` whose response (``Band.support``) lies inside both the detector
    range and the fine dataset's span ``within``."""
    lo, hi = max(range_nm[0], within[0]), min(range_nm[1], within[1])
    out = []
    for c in np.arange(range_nm[0], range_nm[1] + step_nm / 2, step_nm):
        b = Band(float(c), float(fwhm_nm))
        if b.support[0] >= lo - 1e-9 and b.support[1] <= hi + 1e-9:
            out.append(b)
    return out


__all__ = ["RANGES", "DesignRows", "candidates", "fresh_pd", "greedy", "load_design_rows", "proxy_pd", "synthesis"]
