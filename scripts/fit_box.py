"""Fit the tissue model's layer constants so the diffuse model reproduces the rules-detector box.

The thesis's box (b1, b2 on NDGRI; c1, c2 on NDSI) is the range of its diffuse model over skin types I/II to
V/VI. Our absorption tables differ from the thesis's (unavailable) ones, so the layer constants (scattering
power laws, thicknesses of the fixed layers, nominal blood fractions) are fitted here by gradient descent
through the differentiable model: the 0.5th/99.5th percentiles of NDGRI and NDSI over a random Fitzpatrick
I-VI population go to the box edges, and the two Table 2 presets go to typical measured spectra. Constants
stay inside literature ranges (bounded by a sigmoid). Prints the fitted ``SkinLayers`` for tissue.py.

Uses a different seed (12345) from the acceptance test (seed 0). Run: python scripts/fit_box.py
"""

import math

import torch

from torchskin import tissue as T
from torchskin.bands import INDEX_BANDS_NM
from torchskin.detect import DEFAULT_BOX

torch.manual_seed(0)
DT = torch.float64
WL = torch.tensor(INDEX_BANDS_NM, dtype=DT)

# name -> (initial, low, high): bounded, optimised in logit space
SPEC = {
    "a_top": (20.0, 2.0, 80.0),  # reduced scattering at 500 nm of layers 1-3, cm^-1
    "a_mel": (40.0, 5.0, 100.0),  # layers 4-5
    "a_derm": (40.0, 10.0, 80.0),  # dermis 6, 7, 9
    "a_ret": (60.0, 10.0, 120.0),  # reticular per unit collagen fraction
    "b_top": (1.5, 0.5, 3.5),
    "b_mel": (1.5, 0.5, 3.5),
    "b_derm": (2.0, 0.5, 3.5),
    "b_ret": (2.0, 0.5, 3.5),
    "t_top": (1.0, 0.3, 1.5),  # scale of thickness of layers 1-3
    "t_mel": (1.0, 0.5, 2.0),  # scale of thickness of layers 4-5
    "blood6": (0.04, 0.005, 0.1),
    "blood7": (0.15, 0.02, 0.4),
    "blood8": (0.04, 0.005, 0.1),
    "blood9": (0.10, 0.02, 0.3),
    "water_derm": (0.65, 0.5, 0.8),  # water fraction of dermal layers 7-9 (papillary: 0.1 less)
    "water_epi": (0.5, 0.2, 0.7),  # water fraction of the spinosum and basale
}
# typical measured spectra at 544, 633, 1080, 1580 (+1450) for fair and dark skin (soft targets)
TARGETS = {"I-II": [0.33, 0.57, 0.60, 0.085], "V-VI": [0.075, 0.17, 0.45, 0.08]}


def to_logit(x, lo, hi):
    p = (x - lo) / (hi - lo)
    return math.log(p / (1 - p))


INIT = T.fit_values_from_layers(T.DEFAULT_LAYERS)  # the shipped defaults in SPEC's parameterisation: refined here
theta = {
    k: torch.tensor(to_logit(min(max(INIT[k], lo + 1e-3 * (hi - lo)), hi - 1e-3 * (hi - lo)), lo, hi), dtype=DT,
                    requires_grad=True)
    for k, (_, lo, hi) in SPEC.items()
}


def values():
    return {k: lo + (hi - lo) * torch.sigmoid(theta[k]) for k, (_, lo, hi) in SPEC.items()}


def indices(R):
    g, r, n, s = R.unbind(-1)
    return (g - r) / (g + r), (n - s) / (n + s)


PRESET_WEIGHT = 0.2
STEPS = 600
opt = torch.optim.Adam(theta.values(), lr=0.05)
box = DEFAULT_BOX
for step in range(STEPS):
    v = values()
    L = T.layers_from_fit_values(v)
    skins, _ = T.sample(4000, 12345, dtype=DT, layers=L)
    ndgri, ndsi = indices(T.reflectance(skins, WL))
    q = torch.tensor([0.005, 0.995], dtype=DT)
    qg, qs = torch.quantile(ndgri, q), torch.quantile(ndsi, q)
    loss = 10 * ((qg[0] - box.b1) ** 2 + (qg[1] - box.b2) ** 2 + (qs[0] - box.c1) ** 2 + (qs[1] - box.c2) ** 2)
    pr = T.preset(["I-II", "V-VI"], dtype=DT, layers=L)
    Rp = T.reflectance(pr, WL)
    tgt = torch.tensor([TARGETS["I-II"], TARGETS["V-VI"]], dtype=DT)
    loss = loss + ((Rp - tgt) / tgt).pow(2).sum() * PRESET_WEIGHT
    # every named preset inside the box, with a margin
    gi, si = indices(T.reflectance(T.preset(list(T.PRESETS), dtype=DT, layers=L), WL))
    m = 0.02
    hinge = (torch.relu(box.b1 + m - gi) + torch.relu(gi - box.b2 + m) + torch.relu(box.c1 + m - si)
             + torch.relu(si - box.c2 + m))
    loss = loss + 10 * hinge.pow(2).sum()
    opt.zero_grad()
    loss.backward()
    opt.step()
    if step % 50 == 0 or step == STEPS - 1:
        print(step, f"loss {loss.item():.5f}", "ndgri q", [round(x, 4) for x in qg.tolist()],
              "ndsi q", [round(x, 4) for x in qs.tolist()])
        print("   presets", [[round(x, 3) for x in r] for r in Rp.tolist()])
        print("   all presets ndgri", [round(x, 3) for x in gi.tolist()], "ndsi", [round(x, 3) for x in si.tolist()])
v = {k: round(float(x.detach()), 4) for k, x in values().items()}
print(v)
L = T.layers_from_fit_values(v)
for f in ("thickness_cm", "water", "scatter_a500", "scatter_b", "blood"):
    print(f, tuple(round(float(x), 5) for x in getattr(L, f)))
