"""Packaged tables, loaders and band integration."""

import math

import numpy as np
import pytest
import torch

from torchskin import data
from torchskin.bands import Band, band_integrate, band_sampling, parse_bands, response_matrix

DT = torch.float64


def test_tables_are_packaged_and_loaders_interpolate_linearly():
    cols, arr = data.table("water_segelstein")
    assert cols[0] == "wavelength_nm" and arr.shape[1] == 2
    x = torch.tensor(arr[10:14, 0], dtype=DT)
    torch.testing.assert_close(data.water(x), torch.tensor(arr[10:14, 1], dtype=DT))
    mid = 0.5 * (x[:-1] + x[1:])
    torch.testing.assert_close(data.water(mid), torch.tensor(0.5 * (arr[10:13, 1] + arr[11:14, 1]), dtype=DT))


def test_loaders_follow_input_device_dtype_and_shape():
    wl = torch.tensor([[500.0, 600.0], [700.0, 800.0]], dtype=torch.float32)
    w = data.water(wl)
    assert w.shape == (2, 2) and w.dtype == torch.float32


def test_hemoglobin_matches_prahl_and_known_values():
    oxy, deoxy = data.hemoglobin(torch.tensor([542.0, 555.0, 800.0], dtype=DT))
    k = math.log(10) * 150 / 64500
    _, prahl = data.table("hemoglobin_prahl")
    expect_oxy = np.interp([542.0, 555.0, 800.0], prahl[:, 0], prahl[:, 1]) * k
    torch.testing.assert_close(oxy, torch.tensor(expect_oxy, dtype=DT))
    assert float(deoxy[1]) > float(oxy[1])  # deoxy-Hb peak at 555 nm
    # isosbestic point near 800 nm
    assert abs(float(oxy[2] - deoxy[2])) / float(oxy[2]) < 0.1
    # NIR: hemoglobin-only values are non-negative and well below whole blood
    o, d = data.hemoglobin(torch.tensor([1080.0, 1450.0, 1580.0], dtype=DT))
    assert bool((o >= 0).all() and (d >= 0).all()) and float(o[0]) > 1.0
    assert 0.7 < data.blood_water_fraction_bosschaart() < 0.95


def test_melanosome_closed_form_and_range_errors():
    torch.testing.assert_close(data.melanosome(torch.tensor([500.0], dtype=DT)),
                               torch.tensor([6.6e11 * 500**-3.33], dtype=DT))
    with pytest.raises(ValueError, match=r"wavelengths \(table 'water_segelstein'\) must lie in \[250, 2594\] nm"):
        data.water(torch.tensor([100.0]))
    with pytest.raises(ValueError, match="collagen_approx"):
        data.collagen(torch.tensor([1800.0]))


def test_register_table_replaces_a_table():
    before = data.collagen(torch.tensor([600.0], dtype=DT))
    try:
        data.register_table("collagen_approx", [400, 1700], [1.0, 1.0])
        torch.testing.assert_close(data.collagen(torch.tensor([600.0], dtype=DT)), torch.ones(1, dtype=DT))
    finally:
        data.unregister_table("collagen_approx")
    torch.testing.assert_close(data.collagen(torch.tensor([600.0], dtype=DT)), before)
    with pytest.raises(ValueError, match="no registered table 'collagen_approx'"):
        data.unregister_table("collagen_approx")


def test_band_integration_is_a_normalised_average():
    grid = torch.linspace(400, 1700, 1301, dtype=DT)
    bands = parse_bands("544/20,633/20,1080/40,1580/0")
    W = response_matrix(grid, bands)
    torch.testing.assert_close(W.sum(0), torch.ones(4, dtype=DT))
    # constant and linear spectra: a symmetric band returns the value at its centre
    lin = 0.1 + 1e-4 * grid
    out = band_integrate(lin, grid, bands)
    torch.testing.assert_close(out, 0.1 + 1e-4 * torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=DT))
    # the band sampler agrees with integration on a fine grid
    g2, W2 = band_sampling(bands, step_nm=0.5, dtype=DT)
    quad = lambda x: (x - 900) ** 2 / 1e6  # noqa: E731
    torch.testing.assert_close(quad(g2) @ W2, band_integrate(quad(grid), grid, bands), rtol=1e-4, atol=1e-7)


def test_band_errors():
    with pytest.raises(ValueError, match="fwhm_nm"):
        Band(544, -1)
    with pytest.raises(ValueError, match="needs wavelengths"):
        response_matrix(torch.linspace(500, 600, 11), [Band(590, 20)])
    with pytest.raises(ValueError, match="bad band"):
        parse_bands("544,abc")
