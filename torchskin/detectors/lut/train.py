"""The ``lut`` kind's training: a gradient-boosted tree learner (LightGBM) on every normalized difference,
reflectance and brightness of the bands and the configuration (``learner_features``), baked into a
``LookupModel`` table (``bake``) and held to the false-alarm budgets (``tune_threshold``).

Positives are the dataset's skin pixels, sunlit and shadowed. Negatives are its non-skin pixels (clothing,
ground and confusers of the training partition) and the earthlib *train* spectra under random configurations
over the training domain, at random brightness (a Lambertian surface tilted or shaded: times 0.2 to 1.5),
weighing all together at most as much as the dataset's non-skin pixels. Each spectrum's draws form a Latin
hypercube over the configuration and the brightness (``latin_hypercube``): they cover each range evenly. Under a
dataset lit by SPECTRL2, the draws take the dataset's own suns (``training_skies``), and half of them lie in shade:
lit by the sky alone, which tilts a spectrum towards the blue (``SHADE_SHARE``).
LightGBM runs on one thread with ``deterministic=True`` and without row bagging: the same rows and seed give the
same trees on any x86-64 CPU. The seed enters through the earthlib negatives' configurations and brightness, and
through the draw of rows on a dataset larger than ``max_rows``.

The table keeps the learner's score only where skin was seen: in cells of the training skin's coordinates,
widened by ``support_dilation`` cells along every axis. Elsewhere it is 0, never skin, whatever the trees
extrapolate to. It also keeps a margin from the earthlib *train* spectra (``earthlib_cells``): the cells they
fall in at any brightness, widened by ``earthlib_margin`` steps, are never skin, so that a material like one of
them (the test partition's paints, say) is not taken for skin where the trees drew the border close to it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ...bands import BandSet
from ..features import (
    DIFFUSE_SHARE,
    FEATURES,
    MIN_REFLECTANCE,
    diffuse_share,
    domain_from_manifest,
    earthlib_reflectance,
    feature_columns,
    stack_features,
)
from .grid import bits, cell_centres, coordinates, reflectance_of
from .model import EARTHLIB_MARGIN, EVEN_ODDS_LEVEL, LookupModel, to_levels

#: the learner's settings (LightGBM; ``trees`` rounds): one setting, not tuned per dataset. No row bagging: with it
#: the training seed moved the results more than issue 40 allows (docs/benchmarks.md). ``max_delta_step`` and
#: ``lambda_l2`` bound each leaf's output: without them, leaves of rows classified with near certainty (hessian near
#: 0) take Newton steps of thousands of log-odds units, and the table's levels saturate on non-skin cells
LEARNER = {"objective": "binary", "learning_rate": 0.1, "num_leaves": 63, "min_data_in_leaf": 50,
           "max_delta_step": 2.0, "lambda_l2": 1.0,
           "deterministic": True, "force_row_wise": True,
           "num_threads": 1, "verbose": -1}
#: learners per training, each on its own draw of the earthlib negatives; the table holds their mean score. On
#: ``make demo``'s data one learner left five training seeds 0.0108 apart in Pd at sun >= 60 degrees (the draw moves
#: single cells' scores, and the calibrated level with them); two brought that to 0.0057, but 0.0114 once half the
#: negatives lay in shade; four, 0.0082 (docs/benchmarks.md). Two learners fit at a time on two cores
ENSEMBLE = 4
#: the most draws of the earthlib train spectra (each spectrum under its own random configuration and brightness
#: per draw); fewer for a small dataset: about as many rows as the dataset has
EARTHLIB_DRAWS = 100
#: brightness range of the earthlib negatives (a factor on the measured spectrum)
EARTHLIB_SCALE = (0.2, 1.5)
#: the share of each earthlib spectrum's draws that lie in shade, given the training suns (``training_skies``). A
#: surface in shade reads, after the empirical line (fitted on sunlit panels), its reflectance times its sky view V
#: times the sky's share of the panels' light in each band: the blue sky makes that share fall from 544 to 1580 nm,
#: and a shaded bare soil can take skin's NDSI. The draws take the whole diffuse light (``Skies.sky``) and no light
#: from the ground; a cast shadow, which also hides the sky around the sun, is darker and bluer (``Skies.shadow``).
#: Measured with ``scripts/shade_check.py`` (docs/benchmarks.md): the earthlib test spectra the table calls skin in
#: this shade 3.6e-2 with flat draws only, 2.3e-3 with these; in a cast shadow 4.4e-3 and 3.2e-3
SHADE_SHARE = 0.5
#: the sky view V of a shaded earthlib draw (uniform)
SKY_VIEW = (0.3, 1.0)
#: brightness factors at which the earthlib train spectra are placed in the table for the margin
#: (``earthlib_cells``): log-spaced from a deep shadow to a surface facing the sun at twice the panels' light
MARGIN_SCALES = (0.05, 2.0, 40)
#: the share of the training skin's coordinates per axis left outside the table's range (each side)
RANGE_QUANTILE = 1e-4
#: rows per LightGBM predict call while baking
BAKE_CHUNK = 1 << 20


def learner_features(R: np.ndarray, X: np.ndarray) -> np.ndarray:
    """The learner's inputs (N, n + n(n-1)/2 + 1 + k) float64: the n reflectances, every normalized difference
    (a - b) / (a + b) of two bands (0 where a + b is 0), the log of the band sum, the configuration."""
    R = np.maximum(np.asarray(R, np.float64), 0.0)
    n = R.shape[1]
    nd = []
    for i in range(n):
        for j in range(i + 1, n):
            s = R[:, i] + R[:, j]
            nd.append(np.divide(R[:, i] - R[:, j], s, out=np.zeros_like(s), where=s > 0))
    log_b = np.log(np.maximum(R.sum(1), 1e-9))
    nds = np.stack(nd, 1) if nd else np.zeros((len(R), 0))  # one band: no difference (the band design's k = 1)
    return np.concatenate([R, nds, log_b[:, None], np.asarray(X, np.float64)], 1)


@dataclass(frozen=True)
class Skies:
    """The light of a dataset's suns (``training_skies``), sorted by zenith, float64: each sun's zenith (S,) in
    degrees, its diffuse share at 544 nm (S,) (the ``diffuse_share`` feature; NaN where the dataset has no band
    there), the sky's share of an open horizontal surface's light, D / (B cos(zenith) + D), in each band (S, n), the
    circumsolar part of D included (``sky``; what the earthlib negatives in shade take), and the share of the
    isotropic sky alone (``shadow``, (S, n)): what a cast shadow receives from the sky per unit of sky view, as the
    renderer shades it (``render.light``)."""

    zenith_deg: torch.Tensor
    diffuse_share: torch.Tensor
    sky: torch.Tensor
    shadow: torch.Tensor


def training_skies(data_dir: Any, frames: str, bands: BandSet) -> Skies | None:
    """The ``Skies`` of a dataset's suns (the frames ``frames`` names): each distinct sun's zenith and atmosphere
    through the SPECTRL2 light model (``render.light.light_tables``) in ``bands``. None for a dataset under another
    light model (the "thesis" lamp's grey sky tilts nothing)."""
    from ...dataset.config import LIGHT_ATMOSPHERE
    from ...dataset.files import manifest, read_rows
    from ...render.light import light_tables
    from ...render.scene import Atmosphere, Sun

    if (manifest(data_dir) or {}).get("light_model") != "spectrl2":
        return None
    rows = read_rows(data_dir, ["group", "sun", "sun_zenith_deg", "sky_fraction", *LIGHT_ATMOSPHERE], frames)
    key = rows["group"].astype(np.int64) * 65536 + rows["sun"].astype(np.int64)
    first = np.unique(key, return_index=True)[1]
    zen = rows["sun_zenith_deg"][first].astype(np.float64)
    order = np.argsort(zen, kind="stable")
    first, zen = first[order], zen[order]

    def atmosphere(i: int) -> Atmosphere:
        values: dict[str, Any] = {k: int(rows[k][i]) if k == "day_of_year" else float(rows[k][i])
                                  for k in LIGHT_ATMOSPHERE}
        return Atmosphere(**values)

    suns = [Sun(zenith_deg=float(rows["sun_zenith_deg"][i]), atmosphere=atmosphere(i)) for i in first]
    lt = light_tables("spectrl2", suns, bands.bands)
    share = diffuse_share(rows["sky_fraction"][first], rows["sun_zenith_deg"][first]).astype(np.float64)
    glob = lt.direct_horizontal + lt.diffuse_horizontal
    return Skies(torch.from_numpy(zen), torch.from_numpy(share), lt.diffuse_horizontal / glob, lt.sky / glob)


def earthlib_negatives(C: torch.Tensor, domain: torch.Tensor, rows: int, nonskin: int, g: torch.Generator,
                       skies: Skies | None = None, features: Sequence[str] = FEATURES
                       ) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The learner's earthlib negatives: the spectra ``C`` (m, n) drawn ``EARTHLIB_DRAWS`` times at most (about
    ``rows`` rows in all), each under a random configuration of ``domain`` (k, 2; the columns ``features``) and a
    random brightness (``EARTHLIB_SCALE``, log-uniform), from ``g``: a Latin hypercube of draws per spectrum.

    With ``skies``, each draw takes one of those suns (its zenith and diffuse share, stratified by zenith), and a
    ``SHADE_SHARE`` of each spectrum's draws lie in shade: the spectrum times a sky view (``SKY_VIEW``) times the
    sun's sky share in each band, in place of the brightness. Returns reflectance, configuration and the weight of
    each: all together they weigh at most as much as the dataset's ``nonskin`` pixels."""
    lo_c, hi_c = domain[:, 0], domain[:, 1]
    k = len(lo_c)
    draws = min(EARTHLIB_DRAWS, max(1, round(rows / len(C))))
    m = len(C) * draws
    has_zenith = "sun_zenith_deg" in features
    dims = k + 1 + (0 if skies is None else 1 if has_zenith else 2)  # without a zenith column the sun has its own
    u = latin_hypercube(len(C), draws, dims, g).to(C.dtype)  # (draws, m / draws, dims)
    XC = lo_c + (hi_c - lo_c) * u[..., :k].reshape(m, -1)
    a, b = EARTHLIB_SCALE
    base = C.repeat(draws, 1)  # each draw's spectrum
    RC = base * (a * (b / a) ** u[..., k:k + 1].reshape(m, 1))
    if skies is not None:
        if skies.sky.shape[1] != C.shape[1]:
            raise ValueError(f"the training suns' sky shares hold {skies.sky.shape[1]} bands, the spectra "
                             f"{C.shape[1]}")
        zen = list(features).index("sun_zenith_deg") if has_zenith else k + 1
        S = len(skies.zenith_deg)
        j = (u[..., zen].reshape(m) * S).long().clamp_max(S - 1)  # the zenith's stratum picks the sun
        if has_zenith:
            XC[:, zen] = skies.zenith_deg[j].to(C.dtype)
        if DIFFUSE_SHARE in features:
            XC[:, list(features).index(DIFFUSE_SHARE)] = skies.diffuse_share[j].to(C.dtype)
        t = u[..., -1].reshape(m, 1)
        lo, hi = SKY_VIEW
        view = lo + (hi - lo) * (t / SHADE_SHARE).clamp(0, 1)
        RC = torch.where(t < SHADE_SHARE, base * view * skies.sky[j].to(C.dtype), RC)
    return RC, XC, min(1.0, nonskin / m)


def latin_hypercube(groups: int, draws: int, dims: int, g: torch.Generator) -> torch.Tensor:
    """``draws`` points in [0, 1)^``dims`` for each of ``groups``, as (draws, groups, dims): a Latin hypercube per
    group, so each dimension's ``draws`` values fall one in each of its ``draws`` equal strata (in random order, at
    a random place within the stratum). Against independent uniform draws this spreads each spectrum's
    configurations and brightness evenly, so the training seed moves the learned border less."""
    strata = torch.argsort(torch.rand(draws, groups, dims, generator=g), dim=0, stable=True)
    return (strata + torch.rand(draws, groups, dims, generator=g, dtype=torch.float64)) / draws


def table_range(R_skin: torch.Tensor, bins: int) -> tuple[int, list[int], list[int]]:
    """The table's reference band and (shift, lo) per coordinate axis (``grid``). The reference (the brightness
    axis) is the band whose log the training skin spreads least over. Each axis's cell width is the smallest power of
    two (2^shift units) at which the skin's coordinates between the ``RANGE_QUANTILE`` and 1 - ``RANGE_QUANTILE``
    quantiles span at most ``bins - 5`` cells; ``lo`` puts two cells below them (one, and ``bins - 3`` cells, for
    fewer than 9 bins). The skin then lies off the edge cells (never skin) on both sides."""
    R_skin = R_skin.float()
    R_skin = R_skin[(R_skin > 0).all(1)]
    pick = torch.randperm(len(R_skin), generator=torch.Generator().manual_seed(0))[:1 << 22]  # torch.quantile's limit
    q = torch.tensor([RANGE_QUANTILE, 1 - RANGE_QUANTILE], dtype=torch.float64)
    lo, hi = torch.quantile(bits(R_skin[pick]).double(), q, dim=0)
    ref = int(torch.argmin(hi - lo))
    lo, hi = torch.quantile(coordinates(R_skin[pick], ref).double(), q, dim=0)  # exact: below 2^53
    below = 2 if bins >= 9 else 1  # cells below the skin's range, the edge cell included
    span = max(1, bins - 2 * below - 1)  # floor(hi / w) - floor(lo / w) <= span + 1: the last cell stays free
    shift, first = [], []
    for a, b in zip(lo.tolist(), hi.tolist()):
        s = max(0, math.ceil(math.log2(max(b - a, 1.0) / span)))
        shift.append(s)
        first.append(math.floor(a / 2 ** s) - below)
    return ref, shift, first


def earthlib_cells(model: LookupModel, spectra: torch.Tensor, margin: int) -> torch.Tensor:
    """The cells (bins ** n,) bool within ``margin`` steps of an earthlib spectrum (m, n) at any brightness
    (``MARGIN_SCALES``): each step adds the neighbours along one axis at a time (a cross, not a cube: 2n
    neighbours a step). Measured on ``make demo``'s data, a margin of 1 kept a test-partition paint out (22 false
    alarms on one fresh set, 1.3e-4 of its non-skin pixels after) for 0.003 of sunlit skin (docs/benchmarks.md)."""
    a, b, k = MARGIN_SCALES
    scales = torch.logspace(math.log10(a), math.log10(b), k)
    R = (spectra.float()[:, None, :] * scales[None, :, None]).reshape(-1, spectra.shape[1])
    grid = torch.zeros(model.bins ** model.n_bands, dtype=torch.bool)
    grid[model.cells_of(R)] = True
    grid = grid.reshape((model.bins,) * model.n_bands)
    for _ in range(margin):
        out = grid.clone()
        for axis in range(model.n_bands):
            out |= _grown(grid, axis)
        grid = out
    return grid.reshape(-1)


def _grown(grid: torch.Tensor, axis: int) -> torch.Tensor:
    """``grid`` (bool) with each set cell's two neighbours along ``axis`` set too."""
    out = grid.clone()
    lo = [slice(None)] * grid.ndim
    hi = [slice(None)] * grid.ndim
    lo[axis], hi[axis] = slice(0, -1), slice(1, None)
    out[tuple(lo)] |= grid[tuple(hi)]
    out[tuple(hi)] |= grid[tuple(lo)]
    return out


def support(model: LookupModel, R_skin: torch.Tensor, dilation: int) -> torch.Tensor:
    """The cells (bins ** n,) bool holding a training skin pixel, widened by ``dilation`` cells along every
    axis (a cube neighbourhood), without the edge cells of any axis: those also hold every pixel beyond the
    table's range (clipped into them), which is never skin."""
    occ = torch.zeros(model.bins ** model.n_bands, dtype=torch.bool)
    occ[model.cells_of(R_skin)] = True
    grid = occ.reshape((model.bins,) * model.n_bands)
    for axis in range(model.n_bands):
        for _ in range(dilation):
            grid = _grown(grid, axis)
    for axis in range(model.n_bands):
        edge = [slice(None)] * grid.ndim
        for i in (0, model.bins - 1):
            edge[axis] = slice(i, i + 1)
            grid[tuple(edge)] = False
    return grid.reshape(-1)


def slice_centres(model: LookupModel) -> torch.Tensor:
    """The configuration (slices, k) at the centre of every table slice, in slice order."""
    axes = [model.cfg_lo[j].double() + (torch.arange(c, dtype=torch.float64) + 0.5) / model.cfg_inv[j].double()
            for j, c in enumerate(model.config_counts)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))


def bake(model: LookupModel, predict: Any, where: torch.Tensor) -> None:
    """Fill ``model.levels``: in the cells ``where`` (bins ** n,) bool, the levels of ``predict`` (learner
    features (N, f) -> raw score (N,)) at each cell's centre under each slice's central configuration; 0 elsewhere
    and where the score is below even odds (no threshold goes there: ``LookupModel.floor_level``)."""
    idx = torch.nonzero(where).squeeze(1)
    R = reflectance_of(cell_centres(model.shift, model.lo, model.bins)[idx], model.ref).numpy()
    model.levels.zero_()
    for s, cfg in enumerate(slice_centres(model).numpy()):
        X = np.broadcast_to(cfg, (len(R), len(cfg)))[:, :len(cfg) if model.config_inputs else 0]
        score = np.concatenate([predict(learner_features(R[a:a + BAKE_CHUNK], X[a:a + BAKE_CHUNK]))
                                for a in range(0, len(R), BAKE_CHUNK)] or [np.zeros(0)])
        lv = to_levels(torch.from_numpy(score))
        model.levels[s, idx] = torch.where(lv >= EVEN_ODDS_LEVEL, lv, torch.zeros_like(lv))


def tune_threshold(model: LookupModel, spectra: torch.Tensor, pfa_budget: float, R_neg: torch.Tensor | None,
                   X_neg: torch.Tensor | None, scene_budget: float | None) -> int:
    """The smallest threshold level, at least ``EVEN_ODDS_LEVEL``, at which at most ``pfa_budget`` of the earthlib
    ``spectra`` (m, n) (those above the brightness floor) are called skin in every table slice (``floor_level``,
    which no calibration goes below) and, with ``scene_budget``, at most that share of the non-skin rows ``R_neg``
    under ``X_neg``. Sets both and returns the threshold."""
    bright = spectra.mean(1) > MIN_REFLECTANCE
    cell = model.cells_of(spectra)
    lv = model.levels[:, cell].int() * bright.int()  # (slices, m)
    allowed = int(math.floor(pfa_budget * spectra.shape[0]))
    need = EVEN_ODDS_LEVEL
    if allowed < spectra.shape[0]:
        need = max(need, int(lv.sort(dim=1, descending=True).values[:, allowed].max()) + 1)
    model.floor_level.fill_(min(need, 255))
    if scene_budget is not None and R_neg is not None and X_neg is not None and len(R_neg):
        model.threshold.fill_(0)
        top = model.level(R_neg, X_neg).sort(descending=True).values
        k = int(math.floor(scene_budget * len(R_neg)))
        if k < len(top):
            need = max(need, int(top[k]) + 1)
    model.threshold.fill_(min(need, 255))
    return int(model.threshold)


def learn(X: Any, R: Any, label: Any, seed: int = 0, domain: Any = None, features: Sequence[str] = FEATURES,
          bins: int = 32, trees: int = 300, support_dilation: int = 1, earthlib_margin: int = EARTHLIB_MARGIN,
          max_rows: int = 3_000_000, ensemble: int = ENSEMBLE,
          pfa_budget: float = 1e-3, scene_budget: float | None = 1e-4, physical: Any = None,
          configuration: bool = True, bands: BandSet | None = None, skies: Skies | None = None
          ) -> tuple[LookupModel, dict]:
    """Learn a ``LookupModel`` from pixels: configuration ``X`` (N, k), ELM reflectance ``R`` (N, n) in the
    bands ``bands`` (default the four index bands), skin ``label`` (N,). Pixels not above the brightness floor and non-finite ones are left out; at most ``max_rows``
    remain (a draw from ``seed``). ``physical`` (N,) bool marks the rows of frames whose ELM reflectance is
    physical (``elm_valid``; default: all): the scene budget is held on their non-skin rows, those the evaluation
    judges, while every row teaches the learner. ``configuration=False`` learns without the configuration: one
    table slice for every sun and camera. ``ensemble`` learners, each on its own draw of the earthlib negatives, are
    baked as their mean score. ``skies`` (``training_skies``) lights the earthlib negatives with the dataset's suns,
    half of them in shade; without it they are lit alike in every band. Returns the model (eval mode) and a
    training summary."""
    check_options(bins, trees, support_dilation, max_rows, torch.as_tensor(R).shape[-1], earthlib_margin)
    if ensemble < 1:
        raise ValueError(f"ensemble must be at least 1 learner, got {ensemble}")
    try:
        import lightgbm as lgb
    except ImportError:
        raise ValueError("--method lut learns with LightGBM: pip install 'torchskin[dataset]' (or lightgbm)") from None
    X, R = torch.as_tensor(X, dtype=torch.float32), torch.as_tensor(R, dtype=torch.float32)
    label = torch.as_tensor(label, dtype=torch.bool)
    physical = torch.ones_like(label) if physical is None else torch.as_tensor(physical, dtype=torch.bool)
    keep = torch.isfinite(X).all(1) & torch.isfinite(R).all(1) & (R.mean(1) > MIN_REFLECTANCE)
    X, R, label, physical = X[keep], R[keep], label[keep], physical[keep]
    g = torch.Generator().manual_seed(seed)
    # the table's range, its skin support and the scene budget come from every row: a seed changes the learner's
    # draw of rows, not where skin was seen (with the support from the draw alone, five training seeds spread by
    # 0.012 in Pd at sun >= 60 degrees; docs/benchmarks.md)
    skin_all, judged_all, X_all, R_all, label_all = R[label], ~label & physical, X, R, label
    if len(R) > max_rows:
        pick = torch.randperm(len(R), generator=g)[:max_rows].sort().values
        X, R, label, physical = X[pick], R[pick], label[pick], physical[pick]
    if int(label.sum()) < 10 or int((~label).sum()) < 10:
        raise ValueError(f"need at least 10 skin and 10 non-skin pixels above the brightness floor, got "
                         f"{int(label.sum())} and {int((~label).sum())}")
    model = LookupModel(R.shape[1], bins, features, domain=domain, bands=bands,
                        **({} if configuration else {"config_counts": (1,) * X.shape[1]}))
    model.config_inputs = bool(configuration)
    k = X.shape[1] if configuration else 0  # the configuration columns the learner takes
    model.set_range(*table_range(skin_all, bins))
    C = earthlib_reflectance("train", model.bands.centers)
    F_rows = learner_features(R.numpy(), X[:, :k].numpy())
    params = {**LEARNER, "seed": int(seed)}

    def fit(draw: tuple[torch.Tensor, torch.Tensor, float]) -> Any:
        RC, XC, wc = draw
        F = np.concatenate([F_rows, learner_features(RC.numpy(), XC[:, :k].numpy())])
        y = np.concatenate([label.numpy(), np.zeros(len(RC), dtype=bool)]).astype(np.float64)
        w = np.concatenate([np.ones(len(R)), np.full(len(RC), wc)])
        return lgb.train(params, lgb.Dataset(F, y, weight=w, free_raw_data=True), num_boost_round=int(trees))

    nonskin = int((~label).sum())
    draws = [earthlib_negatives(C, model.domain, len(R), nonskin, g, skies, model.features) for _ in range(ensemble)]
    # each learner runs on one thread (the same trees on any CPU); the ensemble's learners run side by side
    with ThreadPoolExecutor(max_workers=min(ensemble, os.cpu_count() or 1)) as pool:
        boosters = list(pool.map(fit, draws))
        del draws

        def mean_score(f: np.ndarray) -> np.ndarray:
            scores = list(pool.map(lambda b: b.predict(f, raw_score=True, num_threads=1), boosters))
            return sum(scores[1:], scores[0]) / len(scores)  # summed in a fixed order: the same bytes every run

        where = support(model, skin_all, support_dilation)
        bake(model, mean_score, where)
    near = earthlib_cells(model, C, earthlib_margin) if earthlib_margin >= 0 else torch.zeros_like(where)
    model.levels[:, near] = 0
    model.boosters = [b.model_to_string() for b in boosters]
    thr = tune_threshold(model, C, pfa_budget, R_all[judged_all], X_all[judged_all], scene_budget)
    model.eval()
    with torch.no_grad():
        hit = model.decide(R_all, X_all)
    rows, nonskin_rows = int(label.sum()), nonskin  # the learner's draw
    label, judged = label_all, judged_all
    info = {"method": "lut", "rows": rows, "nonskin_rows": nonskin_rows, "threshold": thr,
            "floor_level": int(model.floor_level),
            "pfa_budget": pfa_budget, "scene_budget": scene_budget, "train_coverage": float(hit[label].float().mean()),
            "pfa_scene_train": float(hit[judged].float().mean()), "support_cells": int(where.sum()),
            "cells": int(where.numel()), "calibration_configs": int(model.levels.shape[0]),
            "earthlib_margin_cells": int((near & where).sum()),
            "options": {"bins": bins, "trees": trees, "support_dilation": support_dilation,
                        "earthlib_margin": earthlib_margin, "max_rows": max_rows, "ensemble": ensemble,
                        "seed": seed, "configuration": bool(configuration), "shade": skies is not None,
                        "diffuse_share": DIFFUSE_SHARE in model.features, "learner": params}}
    return model, info


#: the most cells a table slice may hold: the cell index stays exact in float32 (below 2 ** 24) and 288 slices
#: of uint8 levels (sun, camera and sky bins) stay near 1.2 GB in memory
MAX_CELLS = 1 << 22


def default_bins(n_bands: int) -> int:
    """The table's cells per axis when ``--bins`` is not given: 32, or the most that keeps ``bins ** n_bands`` within
    ``MAX_CELLS`` (21 for five bands, 12 for six, 8 for seven).

    >>> [default_bins(n) for n in (2, 4, 5, 6, 7)]
    [32, 32, 21, 12, 8]
    """
    b = 32
    while b > 2 and b ** n_bands > MAX_CELLS:
        b -= 1
    return b


def check_options(bins: int, trees: int, support_dilation: int, max_rows: int, n_bands: int = 4,
                  earthlib_margin: int = EARTHLIB_MARGIN) -> None:
    """``ValueError`` naming the ``torchskin train`` flag for a table or learner setting out of range, before any
    row is read."""
    if n_bands < 2:
        raise ValueError(f"--method lut needs at least 2 bands (their normalized differences), got {n_bands}")
    if not 2 <= bins or bins ** n_bands > MAX_CELLS:
        top = int(MAX_CELLS ** (1 / n_bands) + 1e-9)
        raise ValueError(f"--bins must lie in [2, {top}] for {n_bands} bands ({MAX_CELLS} cells a slice at most), "
                         f"got {bins}")
    if trees < 1:
        raise ValueError(f"--trees must be at least 1, got {trees}")
    if not 0 <= support_dilation <= bins:  # wider than the table covers every cell already
        raise ValueError(f"--support-dilation must be 0 or more cells, at most --bins ({bins}), got {support_dilation}")
    if not -1 <= earthlib_margin <= bins:
        raise ValueError(f"--earthlib-margin must be -1 (none) or 0 or more steps, at most --bins ({bins}), got "
                         f"{earthlib_margin}")
    if max_rows < 100:
        raise ValueError(f"--max-rows must be at least 100, got {max_rows}")


def load_rows(data_dir: Any, frames: str, features: Sequence[str] = FEATURES
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Training rows of a dataset (the frames ``frames`` names): configuration (N, k) of ``features``, reflectance
    (N, n) in the dataset's bands (``dataset_bands``, in its order), skin label and whether the row's frame has a
    physical ELM (``elm_valid``), numpy."""
    from ...dataset.files import dataset_bands, read_rows

    cols = list(dataset_bands(data_dir).columns)
    rows = read_rows(data_dir, [*feature_columns(features), *cols, "label", "elm_valid"], frames)
    return (stack_features(rows, features), rows.stack(cols, np.float32), rows["label"].astype(bool),
            rows["elm_valid"].astype(bool))


def train_on_dataset(req: Any) -> tuple[LookupModel, dict, str]:
    """``torchskin train --method lut`` on a dataset folder: the rows (every skin pixel, sunlit and shadowed, and
    the non-skin ones), the declared domain, ``learn`` with the request's options."""
    from ...dataset.files import dataset_bands

    o = req.options
    bands = dataset_bands(req.data)
    bins = o["bins"] or default_bins(len(bands))
    check_options(bins, o["trees"], o["support_dilation"], o["max_rows"], len(bands), o["earthlib_margin"])
    features = (*FEATURES, DIFFUSE_SHARE) if o["diffuse_share"] else FEATURES
    X, R, label, physical = load_rows(req.data, req.frames, features)
    no_share = o["diffuse_share"] and not np.isfinite(X[:, -1]).any()
    if no_share:  # sky_fraction is recorded at 544 nm only: a camera without that band trains on the angles
        features, X = FEATURES, X[:, :-1]
    model, info = learn(X, R, label, seed=req.seed, domain=domain_from_manifest(req.data, features), bins=bins,
                        bands=bands, features=features,
                        trees=o["trees"], support_dilation=o["support_dilation"],
                        earthlib_margin=o["earthlib_margin"], max_rows=o["max_rows"],
                        pfa_budget=req.pfa_budget, scene_budget=req.scene_budget if req.use_scene else None,
                        physical=physical, configuration=o["configuration"],
                        skies=training_skies(req.data, req.frames, bands))
    info["frames"] = req.frames
    info["light_classes"] = ["sunlit", "shadow"]
    note = ("; the dataset records no diffuse share (it has no band at 544 nm): the table takes the sun and camera "
            "angles only" if no_share else "")
    text = (f"trained (lut) on {info['rows']} skin and {info['nonskin_rows']} non-skin pixels; table "
            f"{model.levels.shape[0]} slices x {bins_text(model)}, skin support {info['support_cells']} cells; "
            f"threshold level {info['threshold']} for Pfa <= {req.pfa_budget:g} on the earthlib train partition; "
            f"training skin kept {info['train_coverage']:.4f}, scene non-skin {info['pfa_scene_train']:.2e}{note}")
    return model, info, text


def bins_text(model: LookupModel) -> str:
    """The table's cells per slice as text, e.g. "32^4 cells"."""
    return f"{model.bins}^{model.n_bands} cells"


__all__ = ["ENSEMBLE", "EARTHLIB_DRAWS", "EARTHLIB_MARGIN", "EARTHLIB_SCALE", "LEARNER", "MARGIN_SCALES", "MAX_CELLS",
           "SHADE_SHARE", "SKY_VIEW", "Skies", "bake", "check_options", "earthlib_cells", "earthlib_negatives",
           "latin_hypercube", "learn", "learner_features", "load_rows", "slice_centres", "support", "table_range",
           "train_on_dataset", "training_skies", "tune_threshold"]
