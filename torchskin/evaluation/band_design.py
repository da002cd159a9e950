"""Which bands, and how many, detect skin best at the false-alarm budget: a greedy forward search over bands
synthesised from a dataset rendered once at fine spectral sampling, each candidate set scored by a fast proxy
learner on held-out rows.

>>> sorted(RANGES)
['both', 'ingaas', 'silicon']

The proxy is the lookup-table kind without its bake: the kind's learner (LightGBM on the reflectances, every
normalized difference, the log brightness and the configuration: ``detectors.lut.train.learner_features``, with
the earthlib train spectra as negatives) with a few dozen trees at a larger step, each pixel scored at the centre
of its table cell and never skin outside the cells the kind keeps (the training skin's support, less the earthlib
margin). Its score is held-out Pd of sunlit skin at a scene false-alarm budget, the threshold set on the held-out
non-skin rows, as ``calibrate_to_budget`` sets a detector's. It differs from the kind in what it learns from (a
sample of the physical-ELM frames, each pixel under its own configuration rather than its slice's centre) and
ranks sets as the kind does, a little above it (docs/benchmarks.md). The search chooses among many sets on those rows, so the
chosen sets are then scored on a fresh dataset (``fresh_pd``: the threshold from the held-out rows, Pd and Pfa on
the fresh ones). A band is synthesised from the fine dataset's columns through the renderer's band response
(``onboard.band_plan``, ``bands.response_weights``), as a hyperspectral cube is read by ``detect``.

Light: the renderer exposes each band for itself (``render.sensor``: the brightest pixel at 80 % of full well),
so a band deep in a water-vapour absorption (1380 nm: 100 times less sunlight than 1240 nm in wet air) costs
nothing in the datasets, but a real camera needs that much longer an exposure. ``band_light`` gives a band's
clear-sky global horizontal irradiance (SPECTRL2, sun at 60°, the training world's wettest air) and ``candidates``
leave out the bands below ``min_light``.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..bands import Band

#: detector ranges (nm) of the search: silicon, InGaAs, and a camera with both
RANGES = {"silicon": (400.0, 1000.0), "ingaas": (900.0, 1700.0), "both": (400.0, 1700.0)}
#: the sun zenith (degrees) and default precipitable water (cm: the datasets' default upper bound) at which
#: ``band_light`` reads a band's light
LIGHT_ZENITH_DEG = 60.0
LIGHT_WATER_CM = 4.0


@dataclass
class DesignRows:
    """Rows of the fine dataset: training and held-out reflectance at the fine centres (n, m), configuration
    (n, 3), skin label, held-out sunlit skin; optionally a fresh set's (``fresh_pd``); the configuration's training
    domain (``domain``, (3, 2)), over which the proxy draws its earthlib negatives."""

    centres: list[float]
    R: np.ndarray
    X: np.ndarray
    y: np.ndarray
    R_val: np.ndarray
    X_val: np.ndarray
    y_val: np.ndarray
    lit_val: np.ndarray
    fresh: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None  # R, X, y, lit
    domain: np.ndarray | None = None


#: the proxy's learner: the lut kind's (``lut.train.LEARNER``) with a larger step, so that a few dozen trees reach
#: the scores the kind's 300 reach. With the kind's 0.1 and its bounded leaves (``max_delta_step``), 30 trees cap
#: every score near 3.4: most skin and the hardest non-skin rows tie at the cap, and a threshold at the budget
#: keeps almost no skin (the thesis's bands scored 0.001 where the kind keeps 0.985)
PROXY_LEARNER = {"learning_rate": 0.3}


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
    from ..detectors.features import config_buffers, domain_from_manifest

    return DesignRows(list(bands.centers), R, X, y, Rv, Xv, yv, lv, rows(fresh_dir) if fresh_dir else None,
                      config_buffers(FEATURES, domain=domain_from_manifest(train_dir))[2].double().numpy())


def synthesis(centres: Sequence[float], bands: Sequence[Band]) -> np.ndarray:
    """(k, m) weights that give ``bands`` from reflectance sampled at ``centres`` (``onboard.band_plan``)."""
    from ..onboard import band_plan

    plan = band_plan(list(centres), None, list(bands))
    if plan["kind"] == "reorder":
        m = np.zeros((len(bands), len(centres)))
        m[np.arange(len(bands)), plan["order"]] = 1.0
        return m
    return plan["matrix"]


def synthesise(R, W):
    """Bands from fine reflectance ``R`` (n, m) with weights ``W`` (k, m) (``synthesis``; numpy or torch, alike):
    only the columns a band weighs enter its sum, so a non-finite sample outside every band's response stays out."""
    used = (abs(W) > 0).any(0)
    return R[:, used] @ W[:, used].T


def _proxy(rows: DesignRows, bands: Sequence[Band], trees: int, budget: float, seed: int):
    """The proxy on ``bands``: the lut kind without its bake. Its learner is trained as the kind's is (the rows
    and the earthlib train spectra as negatives, ``lut.train.earthlib_negatives``), with few trees; a pixel is
    scored at the centre of its table cell, and never skin outside the cells the kind keeps (the training skin's
    support, less the earthlib margin), as the baked table scores it. Returns the scorer, the held-out scores and
    the threshold: the lowest at which at most ``budget`` of the held-out non-skin rows score above it, never
    below even odds (the kind's floor)."""
    import lightgbm as lgb
    import torch

    from ..bands import BandSet
    from ..detectors.features import earthlib_reflectance
    from ..detectors.lut.grid import axis_centres, reflectance_of
    from ..detectors.lut.model import EARTHLIB_MARGIN, LookupModel
    from ..detectors.lut.train import (
        LEARNER,
        default_bins,
        earthlib_cells,
        earthlib_negatives,
        learner_features,
        support,
        table_range,
    )

    if rows.domain is None:
        raise ValueError("the proxy needs load_design_rows's training domain")
    W = synthesis(rows.centres, bands)
    R = synthesise(rows.R, W)
    C = earthlib_reflectance("train", [b.center_nm for b in bands])  # as the kind reads them
    RC, XC, wc = earthlib_negatives(C.double(), torch.from_numpy(rows.domain), len(R), int((~rows.y).sum()),
                                    torch.Generator().manual_seed(int(seed)))
    F = np.concatenate([learner_features(R, rows.X), learner_features(RC.numpy(), XC.numpy())])
    y = np.concatenate([rows.y, np.zeros(len(RC), dtype=bool)]).astype(np.float64)
    w = np.concatenate([np.ones(len(R)), np.full(len(RC), wc)])
    booster = lgb.train({**LEARNER, **PROXY_LEARNER, "seed": int(seed)}, lgb.Dataset(F, y, weight=w),
                        num_boost_round=int(trees))
    n, bins = len(bands), default_bins(len(bands))
    if n < 2:  # no table of one band (the kind needs two): the learner itself

        def raw(Rf, X):
            return booster.predict(learner_features(synthesise(Rf, W), X), raw_score=True, num_threads=1)

        return raw, *_threshold(raw, rows, budget)
    table = LookupModel(n, bins, bands=BandSet.of(bands), config_counts=(1,) * rows.X.shape[1])  # cells only
    table.set_range(*table_range(torch.from_numpy(R[rows.y]).float(), bins))
    keep = support(table, torch.from_numpy(R[rows.y]).float(), 1) & ~earthlib_cells(table, C, EARTHLIB_MARGIN)
    strides = bins ** torch.arange(n - 1, -1, -1)

    def score(Rf, X):
        Rt = torch.from_numpy(synthesise(Rf, W)).float()
        cell = table.cells_of(Rt)
        q = (cell[:, None] // strides) % bins  # each axis's cell
        centre = reflectance_of(axis_centres(q, table.shift, table.lo), table.ref).numpy()
        s = booster.predict(learner_features(centre, X), raw_score=True, num_threads=1)
        return np.where(keep[cell].numpy(), s, -np.inf)

    return score, *_threshold(score, rows, budget)


def _threshold(score, rows: DesignRows, budget: float) -> tuple[np.ndarray, float]:
    """The held-out scores and the lowest threshold at which at most ``budget`` of the held-out non-skin rows score
    above it, never below even odds (0)."""
    s = score(rows.R_val, rows.X_val)
    top = np.sort(s[~rows.y_val])[::-1]
    k = int(np.floor(budget * len(top)))  # non-skin rows allowed above the threshold
    return s, max(top[k] if k < len(top) else -np.inf, 0.0)


def proxy_pd(rows: DesignRows, bands: Sequence[Band], trees: int = 40, budget: float = 1e-4,
             seed: int = 0) -> dict:
    """Held-out Pd of sunlit skin of the proxy (``_proxy``) on ``bands`` at the scene false-alarm ``budget`` (the
    threshold set on the held-out non-skin rows), and the held-out Pfa it reaches."""
    _, s, thr = _proxy(rows, bands, trees, budget, seed)
    return _held_out_entry(rows, bands, s, thr)


def _held_out_entry(rows: DesignRows, bands: Sequence[Band], s: np.ndarray, thr: float) -> dict:
    """A set's entry: its bands, held-out Pd of sunlit skin and scene Pfa at the threshold ``thr``."""
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
    return {**_held_out_entry(rows, bands, s, thr), "fresh_pd_sunlit": float((f[lit] > thr).mean()),
            "fresh_pfa_scene": float((f[~y] > thr).mean())}


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
               within: tuple[float, float], min_light: float = 0.0, water_cm: float = LIGHT_WATER_CM) -> list[Band]:
    """Bands every ``step_nm`` of ``fwhm_nm`` whose response (``Band.support``) lies inside both the detector
    range and the fine dataset's span ``within``, and whose light (``band_light`` in air of ``water_cm``) is at
    least ``min_light`` W m^-2 nm^-1."""
    lo, hi = max(range_nm[0], within[0]), min(range_nm[1], within[1])
    out = []
    for c in np.arange(range_nm[0], range_nm[1] + step_nm / 2, step_nm):
        b = Band(float(c), float(fwhm_nm))
        if b.support[0] >= lo - 1e-9 and b.support[1] <= hi + 1e-9:
            out.append(b)
    if min_light > 0 and out:
        light = band_light(out, water_cm)
        out = [b for b, e in zip(out, light) if e >= min_light]
    return out



def band_light(bands: Sequence[Band], water_cm: float = LIGHT_WATER_CM) -> list[float]:
    """Each band's clear-sky global horizontal irradiance (direct + diffuse, W m^-2 nm^-1, averaged over its
    response): SPECTRL2 with the sun at ``LIGHT_ZENITH_DEG`` and ``water_cm`` of precipitable water, the other
    atmosphere at its defaults. Near 1380 nm it is ~0.002 in wet air, against ~0.2 at 1240 nm.

    >>> [round(e, 2) for e in band_light([Band(660.0, 20.0), Band(1240.0, 20.0)])]
    [0.66, 0.21]
    """
    from ..render.light import light_tables
    from ..render.scene import Atmosphere, Sun

    t = light_tables("spectrl2", [Sun(zenith_deg=LIGHT_ZENITH_DEG, atmosphere=Atmosphere(precipitable_water_cm=water_cm))],
                     list(bands))
    return [float(x) for x in (t.direct_horizontal + t.diffuse_horizontal)[0]]


def wettest_air(data_dir: str | os.PathLike) -> float:
    """The upper bound of precipitable water (cm) a dataset's configuration drew from (``LIGHT_WATER_CM`` when
    its manifest does not say)."""
    from ..dataset.files import manifest

    man = manifest(data_dir) or {}
    water = man.get("config", {}).get("light", {}).get("precipitable_water_cm")
    return float(max(water)) if isinstance(water, list) and water else LIGHT_WATER_CM


# ------------------------------------------------------------------------------- the detector kind itself
@dataclass
class KindRows:
    """Every row of the three fine datasets, for the detector kind itself (``kind_scores``): the training rows
    (configuration, fine reflectance, label, physical ELM), the held-out and fresh rows as ``evaluate`` reads
    them (``metrics.HeldOut``, reflectance at the fine centres), the training domain."""

    centres: list[float]
    X: np.ndarray
    R: np.ndarray
    label: np.ndarray
    physical: np.ndarray
    heldout: object
    fresh: object
    domain: object


def load_kind_rows(train_dir: str | os.PathLike, heldout_dir: str | os.PathLike,
                   fresh_dir: str | os.PathLike) -> KindRows:
    """The ``KindRows`` of three datasets in the same fine bands (``load_design_rows`` checks them)."""
    from ..dataset.files import dataset_bands
    from ..detectors.features import FEATURES, domain_from_manifest
    from ..detectors.lut.train import load_rows
    from .metrics import held_out

    centres = list(dataset_bands(train_dir).centers)
    X, R, label, physical = load_rows(train_dir, "line")  # as `torchskin train` reads them
    return KindRows(centres, X, R, label, physical, held_out(heldout_dir, list(FEATURES), centres),
                    held_out(fresh_dir, list(FEATURES), centres), domain_from_manifest(train_dir))


def kind_scores(rows: KindRows, bands: Sequence[Band], trees: int = 300, seed: int = 0, scene_budget: float = 1e-4,
                pfa_budget: float = 1e-3) -> dict:
    """The lookup-table detector kind on ``bands`` (synthesised from the fine rows), as ``make demo`` makes and
    judges it: trained on the training rows (``lut.train.learn``, its default table), calibrated to the budgets on
    the held-out rows (``calibrate_to_budget``), judged on the fresh rows as ``evaluate`` judges (Pd by skin
    category, scene and earthlib-test Pfa). The earthlib spectra are read at the band centres."""
    import copy

    import torch

    from ..bands import BandSet
    from ..detectors.features import MIN_REFLECTANCE
    from ..detectors.lut.train import default_bins, learn
    from .calibration import calibration_data
    from .candidates import model_candidate
    from .regions import earthlib_test, judge

    W = synthesis(rows.centres, bands)  # (k, m)
    bs = BandSet.of(bands)
    model, _ = learn(rows.X, synthesise(rows.R, W.astype(np.float32)), rows.label, seed=seed, domain=rows.domain, bins=default_bins(len(bands)),
                     trees=trees, pfa_budget=pfa_budget, scene_budget=scene_budget, physical=rows.physical, bands=bs)
    test_R, test_pts = earthlib_test(bs.centers, indices=False)

    def synthesised(h):
        out = copy.copy(h)
        out.R = synthesise(h.R, torch.from_numpy(W).float())
        return out

    held, fresh = synthesised(rows.heldout), synthesised(rows.fresh)
    model.calibrate_to_budget(calibration_data(held, test_R, test_pts), scene_budget, pfa_budget)
    cand = model_candidate(model, "lut")
    with torch.no_grad():
        j = judge(cand, fresh, test_R, test_pts, MIN_REFLECTANCE)
    s, hi = j.summary(fresh), j.summary(fresh, fresh.sz >= 60)
    return {"pd_sunlit": s["pd_sunlit"], "pd_shadow": s["pd_shadow"], "pd_backlit": s["pd_backlit"],
            "pd_sun_ge_60_mean_over_configs": hi["pd_sunlit_mean_over_configs"], "pfa_scene": s["pfa_scene"],
            "pfa_earthlib": s["pfa"], "threshold": int(model.threshold)}


# ------------------------------------------------------------------------------------------ the whole design
def design(train_dir: str | os.PathLike, heldout_dir: str | os.PathLike, fresh_dir: str | os.PathLike,
           ranges: Sequence[str] = tuple(RANGES), k_max: int = 6, step_nm: float = 20.0, fwhm_nm: float = 20.0,
           trees: int = 30, max_rows: int = 60_000, budget: float = 1e-4, min_light: float = 0.05,
           kind_trees: int | None = 300, compare: Sequence[tuple[str, Sequence[Band]]] = (),
           progress: bool = True) -> dict:
    """The band design: per detector range, the greedy search's best set of k = 1 ... ``k_max`` bands (the proxy
    learner on held-out rows, ``greedy``), each scored on the fresh set by the proxy (``fresh_pd``) and, with
    ``kind_trees``, by the detector kind itself (``kind_scores``; k >= 2: it reads normalized differences); the thesis's four bands by the same procedure.
    Candidates: every ``step_nm`` nm, ``fwhm_nm`` wide, with at least ``min_light`` W m^-2 nm^-1 of light
    (``band_light`` in the training world's wettest air). ``compare``: more (name, bands) sets, a real camera's,
    scored as the thesis's. Returns a JSON-ready dict (``table``, ``figure``)."""
    from tqdm import tqdm

    from ..bands import INDEX_BANDS
    from ..detectors.lut.train import MAX_CELLS, default_bins

    ranges = list(dict.fromkeys(ranges))
    for r in ranges:
        if r not in RANGES:
            raise ValueError(f"--ranges must name {', '.join(RANGES)}, got {r!r}")
    # everything that can refuse is checked before minutes of search
    rows = load_design_rows(train_dir, heldout_dir, max_rows, fresh_dir=fresh_dir)
    within = (min(rows.centres), max(rows.centres))
    spacing = float(np.max(np.diff(rows.centres)))
    if fwhm_nm > 0 and spacing > fwhm_nm / 2 + 1e-9:
        raise ValueError(f"the datasets sample every {spacing:g} nm, too coarse to synthesise bands of --fwhm {fwhm_nm:g} "
                         f"nm (samples at most FWHM / 2 apart: e.g. generate --bands 400:1700:10 for 20 nm bands)")
    warnings = []
    for name, bands in compare:
        if name in (*RANGES, "thesis"):
            raise ValueError(f"--compare {name!r}: name the camera something else than {', '.join(RANGES)} or thesis")
        if len(bands) < 2:
            raise ValueError(f"--compare {name!r}: a camera of two or more bands is expected, got {len(bands)}")
        if default_bins(len(bands)) ** len(bands) > MAX_CELLS:
            raise ValueError(f"--compare {name!r}: {len(bands)} bands are more than the lut table holds ({MAX_CELLS} "
                             "cells a slice: 22 bands at most)")
        for b in bands:
            if b.support[0] < within[0] - 1e-9 or b.support[1] > within[1] + 1e-9:
                raise ValueError(f"--compare {name!r}: its {b.center_nm:g} nm band's response spans {b.support[0]:g}.."
                                 f"{b.support[1]:g} nm, beyond the datasets' {within[0]:g}..{within[1]:g} nm")
        try:
            synthesis(rows.centres, bands)
        except ValueError as e:
            raise ValueError(f"--compare {name!r}: {e}") from None
        narrow = [b for b in bands if 0 < b.fwhm_nm < 2 * spacing]
        if narrow:
            warnings.append(f"--compare {name!r}: its bands of {', '.join(f'{b.fwhm_nm:g}' for b in narrow)} nm FWHM are "
                            f"narrower than twice the datasets' {spacing:g} nm sampling: they are read from samples "
                            "interpolated linearly between them")
    thesis = list(INDEX_BANDS)
    if any(b.center_nm < within[0] or b.center_nm > within[1] for b in thesis):
        warnings.append(f"the datasets span {within[0]:g}..{within[1]:g} nm: the thesis's bands (544, 633, 1080, "
                        "1580 nm) are not scored")
        thesis = []
    water = wettest_air(train_dir)
    pools = {}
    for r in ranges:
        pools[r] = candidates(RANGES[r], step_nm, fwhm_nm, within, min_light, water)
        if len(pools[r]) < k_max:
            raise ValueError(f"range {r}: {len(pools[r])} candidate bands inside the data's {within[0]:g}-{within[1]:g} "
                             f"nm with at least {min_light:g} W m-2 nm-1 of light (--min-light), fewer than --k-max "
                             f"{k_max}")
    kind = load_kind_rows(train_dir, heldout_dir, fresh_dir) if kind_trees else None
    sets: dict[str, list] = {}
    for r in ranges:
        total = sum(len(pools[r]) - k for k in range(k_max))
        with tqdm(total=total, desc=f"search {r}", unit="set", disable=not progress) as bar:
            steps = greedy(rows, pools[r], k_max, trees, budget, progress=bar.update)
        sets[r] = [[Band(c, f) for c, f in st["bands"]] for st in steps]
    named = [(r, k + 1, b) for r, steps in sets.items() for k, b in enumerate(steps)]
    named += [("thesis", 4, thesis)] if thesis else []
    named += [(name, len(bands), list(bands)) for name, bands in compare]
    out: dict = {"options": {"ranges": list(ranges), "k_max": k_max, "step_nm": step_nm, "fwhm_nm": fwhm_nm,
                             "trees": trees, "max_rows": max_rows, "budget": budget, "min_light": min_light,
                             "kind_trees": kind_trees, "light_water_cm": water, "light_zenith_deg": LIGHT_ZENITH_DEG},
                 "data": {"train": str(train_dir), "heldout": str(heldout_dir), "fresh": str(fresh_dir)},
                 "ranges": {r: [] for r in sets}, "thesis": None, "compare": {}, "warnings": warnings}
    for r, k, bands in tqdm(named, desc="score sets", unit="set", disable=not progress):
        entry = {"k": k, **fresh_pd(rows, bands, trees, budget), "light": band_light(bands, water)}
        if kind is not None and kind_trees:  # the lut kind reads normalized differences: two bands at least
            entry["kind"] = kind_scores(kind, bands, kind_trees, scene_budget=budget) if k >= 2 else None
        if r == "thesis":
            out["thesis"] = entry
        elif r not in sets:
            out["compare"][r] = entry
        else:
            out["ranges"][r].append(entry)
    return out


def table(result: dict) -> str:
    """The design as a Markdown table: per range and k, the bands, the proxy's held-out and fresh Pd of sunlit
    skin, the detector kind's fresh Pd (sunlit, shadow, sun >= 60° mean over configurations) and Pfa (scene,
    earthlib), and the dimmest band's light."""
    kind = result["options"].get("kind_trees")
    head = ["range", "k", "bands (centre/FWHM nm)", "proxy held-out Pd sunlit", "proxy fresh Pd sunlit",
            "proxy fresh Pfa scene"]
    if kind:
        head += ["lut fresh Pd sunlit", "shadow", "sun >= 60 m/c", "Pfa scene", "Pfa earthlib"]
    head.append("dimmest band, W m-2 nm-1")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def row(name, e):
        bands = ", ".join(f"{c:g}/{f:g}" if f else f"{c:g}" for c, f in e["bands"])
        cells = [name, str(e["k"]), bands, f"{e['pd_sunlit']:.3f}", f"{e['fresh_pd_sunlit']:.3f}",
                 f"{e['fresh_pfa_scene']:.1e}"]
        if kind and e["kind"] is None:
            cells += ["-"] * 5
        elif kind:
            q = e["kind"]
            cells += [f"{q['pd_sunlit']:.3f}", f"{q['pd_shadow']:.3f}", f"{q['pd_sun_ge_60_mean_over_configs']:.3f}",
                      f"{q['pfa_scene']:.1e}", f"{q['pfa_earthlib']:.1e}"]
        cells.append(f"{min(e['light']):.3f}")
        return "| " + " | ".join(cells) + " |"

    for r, steps in result["ranges"].items():
        lines += [row(r, e) for e in steps]
    if result.get("thesis"):
        lines.append(row("thesis", result["thesis"]))
    lines += [row(name, e) for name, e in result.get("compare", {}).items()]
    return "\n".join(lines) + "\n"


def figure(result: dict, path: str | os.PathLike) -> None:
    """Pd of sunlit skin on the fresh set against k per range (the detector kind, solid; the proxy, dashed), the
    thesis's four bands marked."""
    from ..plots import pyplot, save_figure

    plt = pyplot()
    kind = bool(result["options"].get("kind_trees"))
    fig, ax = plt.subplots(figsize=(6.6, 4.4))
    for i, (r, steps) in enumerate(result["ranges"].items()):
        ks = [e["k"] for e in steps]
        lo, hi = RANGES[r]
        if kind:
            scored = [e for e in steps if e["kind"] is not None]
            ax.plot([e["k"] for e in scored], [e["kind"]["pd_sunlit"] for e in scored], "o-", color=f"C{i}",
                    label=f"{r} {lo:g}-{hi:g} nm, lut")
        ax.plot(ks, [e["fresh_pd_sunlit"] for e in steps], "s--" if kind else "o-", color=f"C{i}",
                alpha=0.5 if kind else 1.0, ms=4 if kind else 6, label=f"{r}, proxy" if kind else f"{r} {lo:g}-{hi:g} nm")
    t = result.get("thesis")
    if t:
        ax.plot([4], [t["kind"]["pd_sunlit"] if kind else t["fresh_pd_sunlit"]], "k*", ms=13,
                label="thesis bands 544, 633, 1080, 1580 nm")
    for (name, e), mk in zip(result.get("compare", {}).items(), itertools.cycle("DP^vXhd")):
        ax.plot([e["k"]], [e["kind"]["pd_sunlit"] if kind else e["fresh_pd_sunlit"]], mk, color="0.3", ms=9,
                label=f"{name}: " + ", ".join(f"{c:g}" for c, _ in e["bands"]) + " nm")
    ax.set_xlabel("number of bands k (greedy forward selection)")
    ax.set_ylabel("Pd, sunlit skin of the fresh set")
    ax.set_ylim(0, 1.02)
    ax.set_xticks(range(1, result["options"]["k_max"] + 1))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="lower right")
    o = result["options"]
    ax.set_title(f"Best k bands ({o['fwhm_nm']:g} nm FWHM) at scene Pfa <= {o['budget']:g} (held-out threshold)",
                 fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


__all__ = ["LIGHT_WATER_CM", "LIGHT_ZENITH_DEG", "RANGES", "DesignRows", "KindRows", "band_light", "candidates",
           "design", "figure", "fresh_pd", "greedy", "kind_scores", "load_design_rows", "load_kind_rows", "proxy_pd",
           "synthesis", "synthesise", "table", "wettest_air"]
