"""Fit the skin model's layer constants AND its Fitzpatrick sampling ranges to measured skin (ISSA) and the
rules-detector box at the same time (issue 11, item 3).

``scripts/fit_box.py`` fitted the layer constants only to the index percentiles of the thesis's box.
This script adds the visible shape: the sampled population must contain, for each measured in-vivo spectrum
of the International Skin Spectra Archive (ISSA, 17 Jan 2025 release, ``../shared/data/measured_skin``;
SCI mode, i.e. total reflectance, compared with ``tissue.reflectance`` over 450-740 nm), a model skin close
to it. Gradient descent (Adam, float64) through the differentiable model on

- a soft nearest-neighbour RMSE: for each ISSA training spectrum the softmin over the sampled model skins of
  the RMSE over 450-740 nm (the acceptance metric takes the hard minimum); the 9 African training rows, the
  only dark skin in ISSA, carry 5 % of the weight;
- the box: the 0.5th/99.5th percentiles of NDGRI and NDSI over a large population go to b1, b2, c1, c2
  (steep penalty beyond +-BOX_TOL);
- every named preset inside the box with a 0.02 margin (hinge);
- the NIR that ISSA cannot see: the Table 2 presets keep their 1080/1580 nm total reflectance (hinge on
  NIR_LO..NIR_HI around the values fit_box.py fitted to the thesis's radiometer spectra).

The samples are reparameterised: ``tissue.sample``'s random numbers (type index, then one uniform u per
parameter, drawn exactly as ``tissue.sample`` draws them) are fixed, and each skin parameter is lo + u (hi - lo),
so the population is differentiable in the range bounds. Constants and range bounds are optimised in logit
space inside literature ranges (SPEC, MEL_EDGES, SHARED_RANGES, COMMON below). Blood and oxygenation ranges
are shared by all types (blood does not follow the skin type; per-type ranges with a smoothness penalty were
tried and gained nothing: 0.0126 vs 0.0128). The fit starts from the fit_box.py constants (PREVIOUS),
whatever tissue.py holds, so reruns give the same result.

Fitting uses sample seeds 12345 (ISSA term, 2,000 skins) and 12346 (box term, 8,000 skins) and 1,000 ISSA
rows disjoint from the acceptance draw (1,000 rows picked by ``default_rng(0)``) and from the held test subset
(written to ``tests/data/issa2025_subset.csv``). The acceptance figures at the end use seed 0 and the
acceptance draw, as ``tests/test_tissue.py`` does, with the rounded constants that are printed for tissue.py.
``--figure`` also draws ``docs/issa_fit.png`` (before/after).

Run: .venv/bin/python scripts/fit_skin_layers.py [--figure]   (~80 s on one core of this 2-core machine)
Development script: reads ../shared; not run by the tests.
"""

import argparse
import csv
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch

from torchskin import tissue as T
from torchskin.bands import INDEX_BANDS_NM
from torchskin.detect import DEFAULT_BOX

T0 = time.time()
torch.set_num_threads(1)  # steadier than 2 threads on a shared 2-core machine
DT = torch.float64
ROOT = Path(__file__).resolve().parents[1]
ISSA = ROOT.parent / "shared" / "data" / "measured_skin" / "issa2025_visible.csv"
SUBSET = ROOT / "tests" / "data" / "issa2025_subset.csv"
FIGURE = ROOT / "docs" / "issa_fit.png"
BANDS = torch.tensor(INDEX_BANDS_NM, dtype=DT)
FIT_SEED, ACCEPT_SEED = 12345, 0
N_SAMPLES = 2000  # skins for the ISSA term (as in the acceptance metric)
N_BOX = 8000  # skins for the box percentiles (4 bands only; the 0.5 % tails need many)
N_TRAIN = 1000
STEPS = 400
TYPES = T.FITZPATRICK_TYPES


# ---------------------------------------------------------------------------------------------------- data
def load_issa():
    with open(ISSA) as f:
        rows = list(csv.reader(f))
    hdr, data = rows[0], rows[1:]
    wl = np.array([float(h) for h in hdr[7:]])
    R = np.array([[float(x) for x in r[7:]] for r in data])
    meta = np.array([r[:7] for r in data])
    sel = (wl >= 450) & (wl <= 740)
    return wl[sel], R[:, sel], meta, hdr, data


def test_subset_rows(meta):
    """The held test subset: per ethnicity and body site 3 rows (1 per site for the 18 African rows, so half
    of them stay for fitting), drawn with default_rng(2025): 93 rows."""
    rng = np.random.default_rng(2025)
    out = []
    for eth, site in sorted({(m[3], int(m[6])) for m in meta}):
        idx = np.flatnonzero((meta[:, 3] == eth) & (meta[:, 6] == str(site)))
        out.extend(rng.choice(idx, 1 if eth == "AF" else 3, replace=False).tolist())
    return sorted(out)


WL_NP, R_NP, META, HDR, ROWS = load_issa()
WL = torch.tensor(WL_NP, dtype=DT)
ETH = META[:, 3]
ACCEPT = np.random.default_rng(0).choice(len(R_NP), 1000, replace=False)  # the acceptance draw
HELD = test_subset_rows(META)
_pool = np.setdiff1d(np.arange(len(R_NP)), np.union1d(ACCEPT, HELD))
TRAIN = np.sort(np.random.default_rng(FIT_SEED).choice(_pool, N_TRAIN, replace=False))
R_TRAIN = torch.tensor(R_NP[TRAIN], dtype=DT)
_af = ETH[TRAIN] == "AF"
W_TRAIN = torch.tensor(np.where(_af, 0.05 / max(_af.mean(), 1e-9), 0.95 / (1 - _af.mean())) / N_TRAIN, dtype=DT)


def write_subset():
    SUBSET.parent.mkdir(parents=True, exist_ok=True)
    with open(SUBSET, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(HDR)
        for i in HELD:
            w.writerow(ROWS[i])


# ----------------------------------------------------------------------------------------------- parameters
#: the constants before this fit (scripts/fit_box.py): start of the fit, "before" in the figure
PREVIOUS_LAYERS = T.SkinLayers(
    thickness_cm=(0.00046, 0.00024, 0.00046, 0.00358, 0.00134, 0.015, 0.008, 0.0, 0.01),
    water=(0.15, 0.20, 0.30, 0.70, 0.70, 0.571, 0.671, 0.671, 0.671),
    collagen=(0.60, 0.50, 0.40, 0.20, 0.20, 0.30, 0.30, 0.0, 0.30),
    blood=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0402, 0.0200, 0.0050, 0.0200),
    scatter_a500=(15.2, 15.2, 15.2, 5.00, 5.00, 10.0, 10.0, 111.0, 10.0),
    scatter_b=(3.49, 3.49, 3.49, 1.28, 1.28, 3.50, 3.50, 2.65, 3.50),
)
PREVIOUS_TYPES = {
    "I": {"melanosome": (0.010, 0.030), "blood": (0.05, 1.8), "oxygenation": (0.30, 0.95)},
    "II": {"melanosome": (0.030, 0.060), "blood": (0.1, 1.8), "oxygenation": (0.30, 0.95)},
    "III": {"melanosome": (0.060, 0.110), "blood": (0.2, 1.8), "oxygenation": (0.25, 0.90)},
    "IV": {"melanosome": (0.110, 0.180), "blood": (0.4, 1.8), "oxygenation": (0.20, 0.90)},
    "V": {"melanosome": (0.180, 0.300), "blood": (0.5, 1.8), "oxygenation": (0.15, 0.85)},
    "VI": {"melanosome": (0.300, 0.430), "blood": (0.6, 1.8), "oxygenation": (0.15, 0.80)},
}
PREVIOUS_COMMON = {"reticular_depth": (0.10, 0.25), "collagen": (0.55, 0.85), "subcutaneous_scale": (0.40, 0.80)}

# layer constants: name -> (low, high), optimised in logit space
SPEC = {
    # reduced scattering at 500 nm (cm^-1, effective KM values; floors at 20: "tens of cm^-1"; ex vivo / in
    # vitro epidermis ~25-70, dermis ~20-50, Salomatina 2006: 71 and 46) and power-law exponents
    "a_top": (20.0, 120.0),  # stratum corneum, lucidum, granulosum
    "a_mel": (20.0, 100.0),  # spinosum, basale
    "a_derm": (20.0, 80.0),  # papillary dermis and the two blood nets
    "a_ret": (10.0, 120.0),  # reticular dermis, per unit collagen fraction
    "b_top": (0.5, 4.0),
    "b_mel": (0.5, 4.0),
    "b_derm": (0.5, 4.0),
    "b_ret": (0.5, 4.0),
    "t_top": (0.3, 1.5),  # thickness scale of layers 1-3 (x 15, 8, 15 um)
    "t_mel": (0.8, 2.0),  # thickness scale of layers 4-5 (x 40, 15 um): living epidermis 44-110 um
    # nominal blood volume fractions: 0.2-5 % in the papillary and reticular dermis, up to 10 % in the thin
    # vascular plexus layers (upper and deep blood net; Meglinski & Matcher 2002 use 30 % and 10 %)
    "blood6": (0.002, 0.05),
    "blood7": (0.002, 0.10),
    "blood8": (0.002, 0.05),
    "blood9": (0.002, 0.10),
    "water_derm": (0.55, 0.75),  # dermal water fraction (papillary 0.1 less)
    "water_epi": (0.40, 0.75),  # spinosum and basale
}
# melanosome ranges: one increasing chain of type edges (I lo, I/II, ..., V/VI, VI hi), each edge bounded
# around Jacques's epidermal melanosome fractions (light 1.3-6.3 %: types I-II; moderate 11-16 %: IV; dark
# 18-43 %: V-VI; type III fills the gap between light and moderate)
MEL_EDGES = [(0.013, 0.020), (0.025, 0.045), (0.050, 0.063), (0.10, 0.125), (0.16, 0.19), (0.26, 0.32), (0.38, 0.43)]
# blood level and oxygenation: one range for all types; (low, high) of both its ends
SHARED_RANGES = {"blood": (0.05, 2.0), "oxygenation": (0.10, 0.99)}
# ranges shared by all types: ((bounds of lo), (bounds of hi)); each contains the value the presets use
# (PARAM_DEFAULTS reticular depth 0.15 cm and collagen 0.7; the Table 2 subcutaneous scales 0.46 and 0.72)
COMMON = {
    "reticular_depth": ((0.05, 0.15), (0.15, 0.30)),  # reticular dermis 0.5-3 mm
    "collagen": ((0.40, 0.70), (0.70, 0.95)),
    "subcutaneous_scale": ((0.20, 0.46), (0.72, 1.0)),
}


def logit(x, lo, hi):
    p = min(max((x - lo) / (hi - lo), 1e-3), 1 - 1e-3)
    return math.log(p / (1 - p))


def squash(z, lo, hi):
    return lo + (hi - lo) * torch.sigmoid(z)


def init_theta():
    v = T.fit_values_from_layers(PREVIOUS_LAYERS)
    th = {k: logit(v[k], lo, hi) for k, (lo, hi) in SPEC.items()}
    edges = [PREVIOUS_TYPES["I"]["melanosome"][0]] + [PREVIOUS_TYPES[t]["melanosome"][1] for t in TYPES]
    for i, (lo, hi) in enumerate(MEL_EDGES):
        th[f"mel{i}"] = logit(edges[i], lo, hi)
    for k, (lo, hi) in SHARED_RANGES.items():
        a = min(PREVIOUS_TYPES[t][k][0] for t in TYPES)
        b = max(PREVIOUS_TYPES[t][k][1] for t in TYPES)
        th[f"{k}_lo"] = logit(a, lo, hi)
        th[f"{k}_hi"] = logit((b - a) / (hi - a), 0.0, 1.0)  # hi = lo + (high - lo) * sigmoid
    for k, (blo, bhi) in COMMON.items():
        a, b = PREVIOUS_COMMON[k]
        th[f"{k}_lo"] = logit(a, *blo)
        th[f"{k}_hi"] = logit(b, *bhi)
    return {k: torch.tensor(x, dtype=DT, requires_grad=True) for k, x in th.items()}


def decode(th):
    """theta -> (layer constant values, {type: {param: (lo, hi)}}, {param: (lo, hi)}) as tensors."""
    v = {k: squash(th[k], lo, hi) for k, (lo, hi) in SPEC.items()}
    edges = [squash(th[f"mel{i}"], lo, hi) for i, (lo, hi) in enumerate(MEL_EDGES)]
    shared = {}
    for k, (lo, hi) in SHARED_RANGES.items():
        a = squash(th[f"{k}_lo"], lo, hi)
        shared[k] = (a, a + (hi - a) * torch.sigmoid(th[f"{k}_hi"]))
    ranges = {t: {"melanosome": (edges[j], edges[j + 1]), **shared} for j, t in enumerate(TYPES)}
    common = {k: (squash(th[f"{k}_lo"], *blo), squash(th[f"{k}_hi"], *bhi)) for k, (blo, bhi) in COMMON.items()}
    return v, ranges, common


def layers_from(v):
    """The layer constants of the fitted values ``v`` over PREVIOUS_LAYERS (``tissue.layers_from_fit_values``)."""
    return T.layers_from_fit_values(v, PREVIOUS_LAYERS)


def draws(n, seed):
    """The random numbers ``tissue.sample(n, seed)`` draws, in its order: type index, then one u per parameter."""
    g = torch.Generator()
    g.manual_seed(seed)
    which = torch.randint(len(TYPES), (n,), generator=g)
    u = {k: torch.rand(n, generator=g, dtype=torch.float64) for k in T.PARAM_NAMES}
    return which, u


def population(ranges, common, layers, which, u):
    vals = {}
    for k in T.PARAM_NAMES:
        if k in common:
            lo, hi = common[k]
        else:
            lo = torch.stack([torch.as_tensor(ranges[t][k][0], dtype=DT) for t in TYPES])[which]
            hi = torch.stack([torch.as_tensor(ranges[t][k][1], dtype=DT) for t in TYPES])[which]
        vals[k] = lo + u[k] * (hi - lo)
    return T.SkinParams(**vals, layers=layers)


def presets(ranges, common, layers):
    """All named presets (centres of the type ranges, then the fixed Table 2 fits I-II, V-VI) as one batch."""
    rows = [{k: 0.5 * (torch.as_tensor(lo, dtype=DT) + hi) for k, (lo, hi) in {**ranges[t], **common}.items()}
            for t in TYPES]
    for name in ("I-II", "V-VI"):
        rows.append({k: torch.tensor(T.PRESETS[name].get(k, T.PARAM_DEFAULTS[k]), dtype=DT) for k in T.PARAM_NAMES})
    return T.SkinParams(**{k: torch.stack([r[k] for r in rows]) for k in T.PARAM_NAMES}, layers=layers)


def indices(R):
    g, r, n, s = R.unbind(-1)
    return (g - r) / (g + r), (n - s) / (n + s)


def nearest_rmse(R_meas, R_model):
    return torch.cdist(R_meas, R_model) / math.sqrt(R_meas.shape[-1])


# ------------------------------------------------------------------------------------------------- the fit
BOX = DEFAULT_BOX
Q = torch.tensor([0.005, 0.995], dtype=DT)
TAU = 0.003  # softmin temperature on the RMSE
W_BOX, W_HINGE, W_NIR = 1.0, 10.0, 10.0
BOX_TOL = 0.01  # the percentiles may leave the box edges by this much before the steep penalty
# allowed total reflectance of the Table 2 presets I-II, V-VI at 1080, 1580 nm (hinge)
NIR_LO = torch.tensor([[0.53, 0.083], [0.43, 0.078]], dtype=DT)
NIR_HI = torch.tensor([[0.60, 0.088], [0.50, 0.085]], dtype=DT)


def loss_fn(th, fit_draws, box_draws):
    v, ranges, common = decode(th)
    layers = layers_from(v)
    d = nearest_rmse(R_TRAIN, T.reflectance(population(ranges, common, layers, *fit_draws), WL))
    soft = -TAU * torch.logsumexp(-d / TAU, dim=1) + TAU * math.log(d.shape[1])
    fit = (W_TRAIN * soft).sum()
    g, s = indices(T.reflectance(population(ranges, common, layers, *box_draws), BANDS))
    qg, qs = torch.quantile(g, Q), torch.quantile(s, Q)
    dev = torch.stack([qg[0] - BOX.b1, qg[1] - BOX.b2, qs[0] - BOX.c1, qs[1] - BOX.c2])
    box = (torch.relu(dev.abs() - BOX_TOL).pow(2) * 100 + dev.pow(2)).sum()
    Rp = T.reflectance(presets(ranges, common, layers), BANDS)
    gi, si = indices(Rp)
    m = 0.02
    hinge = (torch.relu(BOX.b1 + m - gi) + torch.relu(gi - BOX.b2 + m) + torch.relu(BOX.c1 + m - si)
             + torch.relu(si - BOX.c2 + m)).pow(2).sum()
    nir = (torch.relu(NIR_LO - Rp[-2:, 2:]) + torch.relu(Rp[-2:, 2:] - NIR_HI)).div(NIR_LO).pow(2).sum()
    total = fit + W_BOX * box + W_HINGE * hinge + W_NIR * nir
    parts = {"fit": fit.item(), "hard": d.min(1).values.median().item(), "box": box.item(), "hinge": hinge.item(),
             "nir": nir.item()}
    return total, parts, (qg, qs)


def fit():
    th = init_theta()
    fit_draws, box_draws = draws(N_SAMPLES, FIT_SEED), draws(N_BOX, FIT_SEED + 1)
    opt = torch.optim.Adam(th.values(), lr=0.05)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, STEPS, eta_min=0.005)
    for step in range(STEPS):
        loss, parts, (qg, qs) = loss_fn(th, fit_draws, box_draws)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 50 == 0 or step == STEPS - 1:
            print(f"{step:4d} loss {loss.item():.5f}", {k: round(x, 5) for k, x in parts.items()},
                  "ndgri", [round(x, 4) for x in qg.tolist()], "ndsi", [round(x, 4) for x in qs.tolist()],
                  f"{time.time() - T0:.0f} s", flush=True)
    with torch.no_grad():
        return decode(th)


# ---------------------------------------------------------------------------------------------- reporting
LAYER_FIELDS = ("thickness_cm", "water", "blood", "scatter_a500", "scatter_b")


def rounded(v, ranges, common):
    """Constants as printed for tissue.py (4 decimals; thicknesses 0.1 um): what the acceptance uses."""
    L = layers_from({k: float(x) for k, x in v.items()})
    nd = {"thickness_cm": 6}
    L = dataclasses.replace(L, **{f: tuple(round(float(x), nd.get(f, 4)) for x in getattr(L, f)) for f in LAYER_FIELDS})
    rt = {t: {k: (round(float(a), 4), round(float(b), 4)) for k, (a, b) in ranges[t].items()} for t in TYPES}
    rc = {k: (round(float(a), 4), round(float(b), 4)) for k, (a, b) in common.items()}
    return L, rt, rc


def print_constants(L, rt, rc):
    print("\n# ---- constants for torchskin/tissue.py ----")
    for f in LAYER_FIELDS:
        print(f"    {f}: tuple = {tuple(getattr(L, f))}")
    print("FITZPATRICK_RANGES = {")
    for t, rr in rt.items():
        print(f'    "{t}": {{' + ", ".join(f'"{k}": {a}' for k, a in rr.items()) + "},")
    print("}\nCOMMON_RANGES = {" + ", ".join(f'"{k}": {a}' for k, a in rc.items()) + "}")


def acceptance_population(L, rt, rc, seed=ACCEPT_SEED, n=N_SAMPLES):
    return population(rt, {k: tuple(torch.tensor(x, dtype=DT) for x in ab) for k, ab in rc.items()}, L,
                      *draws(n, seed))


def acceptance(L, rt, rc):
    """The acceptance figures with the rounded constants, drawn exactly as tissue.sample(2000, 0) draws."""
    with torch.no_grad():
        pop = acceptance_population(L, rt, rc)
        Rm = T.reflectance(pop, WL)
        near = nearest_rmse(torch.tensor(R_NP[ACCEPT], dtype=DT), Rm).min(1).values.numpy()
        print(f"\nacceptance: median nearest RMSE (1000 ISSA, 2000 skins seed 0, 450-740 nm) {np.median(near):.4f}")
        for e in ("CN", "CA", "IQ", "AF"):
            m = ETH[ACCEPT] == e
            print(f"   {e}: n={m.sum():4d} median {np.median(near[m]):.4f}")
        held = nearest_rmse(torch.tensor(R_NP[HELD], dtype=DT), Rm).min(1).values.numpy()
        print(f"test subset ({len(HELD)} rows): median nearest RMSE {np.median(held):.4f}")
        other = [np.median(nearest_rmse(torch.tensor(R_NP[np.random.default_rng(s).choice(len(R_NP), 1000,
                 replace=False)], dtype=DT), T.reflectance(acceptance_population(L, rt, rc, seed=s), WL))
                 .min(1).values.numpy()) for s in range(1, 6)]
        print("other seeds 1-5 (skins and ISSA draw):", " ".join(f"{x:.4f}" for x in other))
        g, s = indices(T.reflectance(pop, BANDS))
        qg, qs = torch.quantile(g, Q), torch.quantile(s, Q)
        print(f"NDGRI 0.5/99.5 %: {qg[0]:.4f} {qg[1]:.4f} (box {BOX.b1}, {BOX.b2}); "
              f"NDSI: {qs[0]:.4f} {qs[1]:.4f} (box {BOX.c1}, {BOX.c2})")
        Rp = T.reflectance(presets(rt, {k: tuple(torch.tensor(x, dtype=DT) for x in ab) for k, ab in rc.items()},
                                   L), BANDS)
        gi, si = indices(Rp)
        for name, row, a, b in zip(list(TYPES) + ["I-II", "V-VI"], Rp.tolist(), gi.tolist(), si.tolist()):
            inside = BOX.b1 <= a <= BOX.b2 and BOX.c1 <= b <= BOX.c2
            print(f"   {name:5s} R(544,633,1080,1580) {[round(x, 3) for x in row]} NDGRI {a:.3f} NDSI {b:.3f} "
                  f"{'inside' if inside else 'OUTSIDE'}")
    return near


def figure(L, rt, rc):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with torch.no_grad():
        Rt = torch.tensor(R_NP[ACCEPT], dtype=DT)
        before_pop = acceptance_population(PREVIOUS_LAYERS, PREVIOUS_TYPES, PREVIOUS_COMMON)
        Rb = T.reflectance(before_pop, WL)
        Ra = T.reflectance(acceptance_population(L, rt, rc), WL)
        db, da = nearest_rmse(Rt, Rb).min(1), nearest_rmse(Rt, Ra).min(1)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.2))
    colors = {"CN": "tab:orange", "CA": "tab:blue", "IQ": "tab:green", "AF": "tab:brown"}
    names = {"CN": "Chinese", "CA": "Caucasian", "IQ": "Iraqi", "AF": "African"}
    for e, c in colors.items():
        rows = np.flatnonzero(ETH[ACCEPT] == e)
        order = rows[np.argsort(da.values.numpy()[rows])]
        for j, i in enumerate([order[len(order) // 4], order[(3 * len(order)) // 4]] if len(order) > 2 else order[:2]):
            ax.plot(WL_NP, R_NP[ACCEPT[i]], color=c, lw=1.8, label=f"ISSA {names[e]}" if j == 0 else None)
            ax.plot(WL_NP, Ra[da.indices[i]].numpy(), color=c, lw=1.3, ls="--",
                    label="nearest model skin (after)" if (e == "CN" and j == 0) else None)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("total reflectance (specular included)")
    ax.set_title("ISSA spectra (25th/75th-percentile fits per group)\nand their nearest calibrated model skins")
    ax.set_xlim(450, 740)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    bins = np.linspace(0, 0.08, 41)
    bx.hist(db.values.numpy(), bins=bins, alpha=0.6, color="tab:gray",
            label=f"before (fit_box.py): median {db.values.median():.4f}")
    bx.hist(da.values.numpy(), bins=bins, alpha=0.6, color="tab:red",
            label=f"after (fit_skin_layers.py): median {da.values.median():.4f}")
    bx.axvline(0.015, color="k", ls=":", label="acceptance: median <= 0.015")
    bx.set_xlabel("RMSE to the nearest model skin, 450-740 nm (reflectance)")
    bx.set_ylabel("ISSA spectra (of 1,000)")
    bx.set_title("1,000 ISSA spectra vs 2,000 model skins (tissue.sample seed 0)")
    bx.legend(fontsize=8)
    bx.grid(alpha=0.3)
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=110)
    print(f"wrote {FIGURE}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--figure", action="store_true", help=f"also draw {FIGURE.relative_to(ROOT)}")
    args = ap.parse_args()
    write_subset()
    L, rt, rc = rounded(*fit())
    print_constants(L, rt, rc)
    acceptance(L, rt, rc)
    if args.figure:
        figure(L, rt, rc)
    print(f"runtime {time.time() - T0:.1f} s")


if __name__ == "__main__":
    main()
