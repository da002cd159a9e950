"""Kubelka-Munk layer physics and layer adding."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchskin import tissue as T

DT = torch.float64


def t(x):
    return torch.tensor(x, dtype=DT)


def test_non_absorbing_layer_conserves_energy_and_matches_closed_form():
    S = t([0.1, 1.0, 10.0, 100.0])
    d = t(0.05)
    r, tau = T.km_layer(torch.zeros_like(S), S, d)
    torch.testing.assert_close(r + tau, torch.ones_like(S), atol=1e-12, rtol=0)
    torch.testing.assert_close(r, S * d / (1 + S * d), atol=1e-12, rtol=0)


def test_thick_layer_gives_r_infinity():
    K = t([0.01, 0.5, 3.0, 40.0])
    S = t([10.0, 5.0, 2.0, 1.0])
    r, tau = T.km_layer(K, S, t(1e3))
    ks = K / S
    r_inf = 1 + ks - torch.sqrt(ks**2 + 2 * ks)
    torch.testing.assert_close(r, r_inf, atol=1e-12, rtol=0)
    assert float(tau.max()) < 1e-12


def test_matches_kubelka_hyperbolic_form():
    """The overflow-free form equals Kubelka's r = sinh/(a sinh + b cosh) (the corrected eq 2.4.8-2.4.9)."""
    K, S, d = t([0.3, 2.0, 7.0]), t([5.0, 3.0, 1.5]), t([0.02, 0.1, 0.3])
    a = (S + K) / S
    b = torch.sqrt(a * a - 1)
    x = b * S * d
    den = a * torch.sinh(x) + b * torch.cosh(x)
    r, tau = T.km_layer(K, S, d)
    torch.testing.assert_close(r, torch.sinh(x) / den, atol=1e-13, rtol=0)
    torch.testing.assert_close(tau, b / den, atol=1e-13, rtol=0)


def test_pure_absorber_transmits_exponentially():
    K, d = t([0.5, 2.0]), t(0.3)
    r, tau = T.km_layer(K, torch.zeros_like(K), d)
    torch.testing.assert_close(r, torch.zeros_like(K))
    torch.testing.assert_close(tau, torch.exp(-K * d))


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(
    K=st.floats(0, 1e3), S=st.floats(1e-3, 1e3), d=st.floats(1e-5, 10.0),
    mua=st.floats(0, 1e3), mus=st.floats(1e-3, 1e3), Rb=st.floats(0, 1),
)
def test_reflectance_and_transmittance_in_unit_interval(K, S, d, mua, mus, Rb):
    for dt in (torch.float32, torch.float64):
        r, tau = T.km_layer(torch.tensor(K, dtype=dt), torch.tensor(S, dtype=dt), torch.tensor(d, dtype=dt))
        assert 0 <= float(r) <= 1 and 0 <= float(tau) <= 1
        assert float(r + tau) <= 1 + 1e-6  # absorption >= 0
        R = T.km_over(torch.tensor(mua, dtype=dt), torch.tensor(mus, dtype=dt), torch.tensor(d, dtype=dt),
                      torch.tensor(Rb, dtype=dt))
        assert 0 <= float(R) <= 1 + 1e-6


def _random_layer(g, n):
    K = torch.rand(n, generator=g, dtype=DT) * 5
    S = torch.rand(n, generator=g, dtype=DT) * 50 + 0.1
    d = torch.rand(n, generator=g, dtype=DT) * 0.05
    r, tau = T.km_layer(K, S, d)
    return (r, r, tau)


def test_layer_adding_is_associative():
    g = torch.Generator().manual_seed(1)
    A, B, C = (_random_layer(g, 100) for _ in range(3))
    left = T.add_layers(T.add_layers(A, B), C)
    right = T.add_layers(A, T.add_layers(B, C))
    for x, y in zip(left, right):
        torch.testing.assert_close(x, y, atol=1e-13, rtol=0)


def test_adding_identical_halves_equals_one_thick_layer():
    K, S, d = torch.tensor(1.3, dtype=DT), torch.tensor(20.0, dtype=DT), torch.tensor(0.04, dtype=DT)
    r, tau = T.km_layer(K, S, d)
    half = T.km_layer(K, S, d / 2)
    R, _, Tt = T.add_layers((half[0], half[0], half[1]), (half[0], half[0], half[1]))
    torch.testing.assert_close(R, r, atol=1e-14, rtol=0)
    torch.testing.assert_close(Tt, tau, atol=1e-14, rtol=0)


def test_fused_layer_equals_composition():
    g = torch.Generator().manual_seed(2)
    mua = torch.rand(500, generator=g, dtype=DT) * 50
    mus = torch.rand(500, generator=g, dtype=DT) * 100 + 0.01
    d = torch.rand(500, generator=g, dtype=DT) * 0.2
    Rb = torch.rand(500, generator=g, dtype=DT)
    r, tau = T.km_layer(*T.km_coefficients(mua, mus), d)
    torch.testing.assert_close(T.km_over(mua, mus, d, Rb), T.add_over_base(r, tau, Rb), atol=1e-13, rtol=0)


def test_km_coefficients_limits():
    """Eqs 2.4.6-2.4.7: K = 2 mu_a, S = 3/4 mu_s' for a scattering-dominated medium."""
    K, S = T.km_coefficients(t(1e-6), t(100.0))
    torch.testing.assert_close(K, t(2e-6), rtol=1e-6, atol=0)
    torch.testing.assert_close(S, t(75.0), rtol=1e-6, atol=0)


@pytest.mark.slow
def test_closed_form_in_r0_equals_recursion_with_surface_first():
    """R_total(R0) = R0 + (1-R0)^2 R_sub/(1-R0 R_sub) equals adding the surface as the first layer, then
    each of the nine layers and the substrate top-down (eqs 2.4.12-2.4.13 with the below-reflectance)."""
    skins, _ = T.sample(64, 3, dtype=DT)
    wl = T.wavelength_grid(400, 1700, 25, dtype=DT)
    for r0 in (0.04, 0.2, 0.7):
        closed = T.total_reflectance(skins, wl, r0=r0)
        R0 = torch.full_like(closed, r0)
        acc = (R0, R0, 1 - R0)  # the surface as layer 0, T0 = 1 - R0
        for r, tau in T.layer_stack(skins, wl):
            acc = T.add_layers(acc, (r, r, tau))
        torch.testing.assert_close(acc[0], closed, atol=1e-10, rtol=0)


def test_bottom_up_model_equals_explicit_per_layer_stack():
    skins, _ = T.sample(32, 4, dtype=DT)
    wl = T.wavelength_grid(400, 1700, 50, dtype=DT)
    stack = T.layer_stack(skins, wl)
    R = stack[-1][0]
    for r, tau in reversed(stack[:-1]):
        R = T.add_over_base(r, tau, R)
    torch.testing.assert_close(T.subsurface_reflectance(skins, wl), R, atol=1e-12, rtol=0)


def test_blocked_cpu_evaluation_equals_single_block(monkeypatch):
    skins, _ = T.sample(300, 5, dtype=DT)
    wl = T.wavelength_grid(400, 1700, 100, dtype=DT)
    full = T.subsurface_reflectance(skins, wl)
    monkeypatch.setattr(T, "CPU_BLOCK", 7 * wl.numel())
    torch.testing.assert_close(T.subsurface_reflectance(skins, wl), full, atol=0, rtol=0)
