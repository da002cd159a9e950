"""The skin model against measured in-vivo skin: a held subset of ISSA 2025 (``tests/data``, 93 spectra over
4 ethnicities x 10 body sites; not used by ``scripts/fit_skin_layers.py``'s fit). ISSA is SCI-mode (specular
included), so it is compared with ``tissue.reflectance``, the total reflectance, over 450-740 nm."""

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchskin import tissue as T

DT = torch.float64
SUBSET = Path(__file__).parent / "data" / "issa2025_subset.csv"


@pytest.fixture(scope="module")
def issa():
    with open(SUBSET) as f:
        rows = list(csv.reader(f))
    wl = np.array([float(h) for h in rows[0][7:]])
    R = np.array([[float(x) for x in r[7:]] for r in rows[1:]])
    sel = (wl >= 450) & (wl <= 740)
    return torch.tensor(wl[sel], dtype=DT), torch.tensor(R[:, sel], dtype=DT), np.array([r[3] for r in rows[1:]])


@pytest.fixture(scope="module")
def nearest(issa):
    """For each ISSA spectrum: RMSE to, and index of, the nearest of ``tissue.sample(2000, 0)``."""
    wl, R, _ = issa
    skins, _ = T.sample(2000, 0, dtype=DT)
    Rm = T.reflectance(skins, wl)
    d, idx = (torch.cdist(R, Rm) / math.sqrt(wl.numel())).min(1)
    return d, idx, skins, Rm


def test_subset_spans_the_archive(issa):
    _, R, eth = issa
    assert R.shape == (93, 30)
    assert set(eth) == {"CN", "CA", "IQ", "AF"}


@pytest.mark.slow
def test_population_covers_measured_skin(issa, nearest):
    """Median RMSE from each ISSA spectrum to the nearest model skin: measured 0.0148 here (0.0133 on the
    acceptance draw of 1,000 ISSA spectra; 0.024 before the ISSA calibration). The subset weights the rare
    African rows (10 % here, 0.3 % in ISSA) and Iraqi rows up, so its median is a little higher."""
    d, *_ = nearest
    assert float(d.median()) <= 0.016, float(d.median())
    assert float((d < 0.03).double().mean()) >= 0.85  # measured 0.91


def test_dark_measured_skin_is_matched_by_melanin_rich_model_skin(issa, nearest):
    """The African spectra (the only dark skin in ISSA) are matched by Jacques's "dark" melanosome fractions
    (>= 18 %; measured 0.28-0.42), the others by less melanin (median 0.13)."""
    _, _, eth = issa
    _, idx, skins, _ = nearest
    mel = skins.melanosome[idx].numpy()
    assert mel[eth == "AF"].min() >= 0.18, mel[eth == "AF"]
    assert np.median(mel[eth != "AF"]) < 0.18


def test_hemoglobin_w_follows_the_data(issa, nearest):
    """The oxy-hemoglobin W (bands at 542 and 576 nm, a local bump at 560 nm): where a measured spectrum shows
    it clearly, its nearest model skin shows it too (measured 52 of 55), and the bump heights correlate
    (measured r = 0.59)."""
    wl, R, _ = issa
    _, idx, _, Rm = nearest
    k = {int(w): i for i, w in enumerate(wl.tolist())}

    def bump(X):
        return (X[:, k[560]] - 0.5 * (X[:, k[550]] + X[:, k[570]])).numpy()

    wd, wm = bump(R), bump(Rm[idx])
    clear = wd > 0.002
    assert clear.sum() >= 40
    assert (wm[clear] > 0).mean() >= 0.85, (wm[clear] > 0).mean()
    assert np.corrcoef(wd, wm)[0, 1] > 0.3
