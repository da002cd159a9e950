"""Fresnel, Schlick, the microfacet lobe, the combined BRDF, observed reflectance and DHR."""

import math

import pytest
import torch

from torchskin import optics as O

DT = torch.float64


def deg(x):
    return torch.as_tensor(x, dtype=DT) * math.pi / 180


def test_fresnel_normal_incidence_air_to_skin_is_004():
    assert abs(float(O.fresnel_normal(torch.tensor(1.0, dtype=DT), 1.5)) - 0.04) < 1e-12
    th = torch.zeros(1, dtype=DT)
    for f in (O.fresnel_s, O.fresnel_p, O.fresnel_unpolarized):
        assert abs(float(f(th, 1.0, 1.5)) - 0.04) < 1e-12


def test_fresnel_polarisations_behave_physically():
    th = deg(torch.linspace(0, 89.9, 500, dtype=DT))
    rs, rp = O.fresnel_s(th), O.fresnel_p(th)
    brewster = math.atan(1.5)
    i = int(torch.argmin(rp))
    assert abs(float(th[i]) - brewster) < deg(0.2)  # p vanishes at Brewster's angle
    assert float(rp.min()) < 1e-5
    assert bool((rs[1:] >= rs[:-1]).all())
    assert float(rs[-1]) > 0.99
    # total internal reflection going out of the skin
    assert float(O.fresnel_s(deg(60.0), 1.5, 1.0)) == 1.0


def test_schlick_matches_exact_fresnel_like_fig3():
    """Fig 3: equal at normal incidence, both rise to 1 at grazing, Schlick stays within 0.02 of the exact
    unpolarised curve below 80 degrees, lies below it through the mid angles (0-70 degrees, as in Fig 3)
    and rises monotonically."""
    th = deg(torch.linspace(0, 90, 181, dtype=DT))
    ex, sc = O.fresnel_unpolarized(th), O.schlick(0.04, th)
    assert abs(float(sc[0] - ex[0])) < 1e-12
    assert abs(float(sc[-1]) - 1) < 1e-12 and abs(float(ex[-1]) - 1) < 1e-6
    below80 = th <= deg(80.0)
    assert float((sc - ex)[below80].abs().max()) < 0.025
    mid = th <= deg(70.0)
    assert bool((sc[mid] <= ex[mid] + 1e-15).all())
    assert bool((sc[1:] >= sc[:-1]).all())


def test_rho0_to_refractive_index_values_of_section_333():
    rho0 = torch.tensor([0.030, 0.038, 0.045, 0.042], dtype=DT)
    n = O.rho0_to_n(rho0)
    torch.testing.assert_close(n, torch.tensor([1.42, 1.48, 1.54, 1.51], dtype=DT), atol=0.01, rtol=0)
    torch.testing.assert_close(O.n_to_rho0(n), rho0, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="rho0"):
        O.rho0_to_n(torch.tensor([1.5]))


def test_microfacet_mirror_geometry():
    beta, theta = O.microfacet_angles(deg(35.0), deg(35.0), math.pi)
    assert abs(float(beta) - float(deg(35.0))) < 1e-9 and abs(float(theta)) < 1e-5


def test_microfacet_reciprocity():
    g = torch.Generator().manual_seed(0)
    ti = torch.rand(2000, generator=g, dtype=DT) * 1.5
    tr = torch.rand(2000, generator=g, dtype=DT) * 1.5
    dp = torch.rand(2000, generator=g, dtype=DT) * 2 * math.pi
    for shadowing in (False, True):
        a = O.microfacet_brdf(ti, tr, dp, 0.02, 0.04, shadowing=shadowing)
        b = O.microfacet_brdf(tr, ti, dp, 0.02, 0.04, shadowing=shadowing)
        torch.testing.assert_close(a, b, rtol=1e-10, atol=0)
    c = O.combined_brdf(ti, tr, dp, 0.4, 0.02, 0.04)
    # the diffuse term of eq 3.1.1 depends on beta only, so the combined BRDF is reciprocal too
    torch.testing.assert_close(c, O.combined_brdf(tr, ti, dp, 0.4, 0.02, 0.04), rtol=1e-10, atol=0)


@pytest.mark.parametrize("theta_i", [0.0, 10.0, 20.0, 30.0])
def test_microfacet_maximum_at_mirror_direction(theta_i):
    """Over the viewing hemisphere (up to 60 degrees) the lobe peaks in the forward plane at the mirror."""
    ti = deg(theta_i)
    tr = deg(torch.linspace(0, 60, 601, dtype=DT))[:, None]
    dp = torch.linspace(0, 2 * math.pi, 73, dtype=DT)[None, :]
    f = O.microfacet_brdf(ti, tr, dp, 0.0146, 0.042)
    i, j = divmod(int(torch.argmax(f)), f.shape[1])
    assert theta_i == 0 or abs(float(dp[0, j]) - math.pi) < 1e-9
    assert abs(float(tr[i, 0]) - float(ti)) <= float(deg(3.0))


@pytest.mark.parametrize("theta_i", [10.0, 40.0, 70.0])
@pytest.mark.parametrize("sigma2", [0.0146, 0.0313])
def test_facet_distribution_peaks_exactly_at_mirror(theta_i, sigma2):
    """f cos(θi) cos(θr) / F(β) is the facet distribution (over 8): maximal exactly at θr = θi, Δφ = π,
    at every incidence. (The thesis's form itself, without shadowing, peaks off-specular towards grazing
    at large incidence through its 1/cos θr factor.)"""
    ti = deg(theta_i)
    tr = deg(torch.linspace(0, 89, 891, dtype=DT))[:, None]
    dp = torch.linspace(0, 2 * math.pi, 73, dtype=DT)[None, :]
    beta, _ = O.microfacet_angles(ti, tr, dp)
    d = O.microfacet_brdf(ti, tr, dp, sigma2, 0.04) * torch.cos(ti) * torch.cos(tr) / O.schlick(0.04, beta)
    i, j = divmod(int(torch.argmax(d)), d.shape[1])
    assert abs(float(dp[0, j]) - math.pi) < 1e-9 and abs(float(tr[i, 0] - ti)) < 1e-9


def _half_max_width(sigma2, theta_i):
    """In-plane angular extent (|θr| <= 85 deg) where the lobe exceeds half its mirror value."""
    tr = deg(torch.linspace(-85, 85, 17001, dtype=DT))  # signed in-plane angle, + = forward side
    f = O.microfacet_brdf(deg(theta_i), tr.abs(), torch.where(tr >= 0, math.pi, 0.0), sigma2, 0.04)
    f_mirror = O.microfacet_brdf(deg(theta_i), deg(theta_i), math.pi, sigma2, 0.04)
    above = tr[f >= f_mirror / 2]
    return float(above.max() - above.min())


@pytest.mark.parametrize("theta_i", [0.0, 20.0, 40.0, 60.0])
def test_in_plane_lobes_of_fig7_widen_with_variance(theta_i):
    widths = [_half_max_width(s2, theta_i) for s2 in (0.01, 0.02, 0.03)]
    assert widths[0] < widths[1] < widths[2], widths


def test_dhr_of_lambertian_and_specular_lobe():
    ti = deg(torch.tensor([0.0, 30.0, 60.0], dtype=DT))
    lam = O.dhr(lambda a, b, c: torch.full(torch.broadcast_shapes(a.shape, b.shape, c.shape), 0.6 / math.pi,
                                          dtype=DT), ti)
    torch.testing.assert_close(lam, torch.full_like(ti, 0.6), atol=1e-12, rtol=0)
    # a narrow lobe at normal incidence reflects ~rho0 into the hemisphere (D integrates to 1)
    spec = O.dhr(lambda a, b, c: O.microfacet_brdf(a, b, c, 0.005, 0.04), torch.zeros(1, dtype=DT), 256, 256)
    assert abs(float(spec) - 0.04) < 0.002


def test_smith_shadowing_keeps_energy_bounded_at_grazing():
    ti = deg(torch.tensor([0.0, 60.0, 80.0, 88.0], dtype=DT))
    fn = lambda s: (lambda a, b, c: O.combined_brdf(a, b, c, 0.5, 0.03, 0.04, shadowing=s))  # noqa: E731
    plain = O.dhr(fn(False), ti, 192, 192)
    smith = O.dhr(fn(True), ti, 192, 192)
    assert bool((smith <= plain + 1e-12).all())
    assert float(smith.max()) <= 1.0
    assert float(plain[-1]) > float(smith[-1]) + 0.05  # without G the lobe blows up at grazing


def test_skin_surface_models_energy():
    """The conserving skin model (ρ_d the subsurface part) with Smith shadowing keeps the DHR <= 1 at every
    incidence, even for a nearly white subsurface; the thesis's model (ρ_d with the front surface) counts the
    surface reflection twice and exceeds 1 towards grazing incidence; at normal incidence the two differ by
    about (1 - ρ0) R0 only."""
    ti = deg(torch.tensor([0.0, 30.0, 60.0, 75.0, 85.0, 89.0], dtype=DT))
    r_sub = torch.tensor([0.05, 0.5, 0.9, 0.99], dtype=DT)[:, None, None, None]  # (R, 1, 1, 1): broadcasts

    def dhr_of(surface, shadowing):
        fn = lambda a, b, c: O.skin_brdf(a, b, c, r_sub, 0.0313, 0.030, surface, shadowing=shadowing)  # noqa: E731
        return O.dhr(fn, ti, 128, 128)  # (R, 6)

    cons = dhr_of("conserving", True)
    assert float(cons.max()) <= 1.0, cons
    thesis = dhr_of("thesis", False)
    assert float(thesis[2:, -1].min()) > 1.0  # bright skin at 89°: more light out than in
    assert bool((thesis > cons).all())
    # at normal incidence the front-surface term adds about (1 - F) R0 = 0.03 to the diffuse part
    assert abs(float((thesis - dhr_of("conserving", False))[1, 0]) - 0.97 * 0.030) < 0.01
    with pytest.raises(ValueError, match="surface must be one of thesis, conserving"):
        O.skin_brdf(0.1, 0.2, 0.3, 0.5, 0.03, 0.04, "lambertian")


def test_observed_reflectance_integrates_to_dhr():
    """Eq 3.1.4 summed over detectors tiling the hemisphere (Ω = sin θ dθ dφ) is the DHR, eq 2.3.2."""
    ti = deg(torch.tensor([20.0], dtype=DT))
    tr, wt = O.gauss_legendre(128, 0, math.pi / 2)
    nphi = 128
    phi = torch.arange(nphi, dtype=DT) * 2 * math.pi / nphi
    f = O.combined_brdf(ti, tr[:, None], phi[None, :], 0.45, 0.0313, 0.030)
    omega = (wt * torch.sin(tr))[:, None] * (2 * math.pi / nphi)
    total = O.observed_reflectance(f, tr[:, None], omega).sum()
    ref = O.dhr(lambda a, b, c: O.combined_brdf(a, b, c, 0.45, 0.0313, 0.030), ti, 128, 128)
    torch.testing.assert_close(total, ref[0], rtol=1e-12, atol=0)
    assert 0.3 < float(total) < 1.0


def test_combined_brdf_lambertian_limit_and_band_defaults():
    sig, rho0 = O.THESIS_SPECULAR.for_bands(dtype=DT)
    torch.testing.assert_close(sig, torch.tensor([0.0313, 0.0292, 0.0214, 0.0146], dtype=DT))
    torch.testing.assert_close(rho0, torch.tensor([0.030, 0.038, 0.045, 0.042], dtype=DT))
    # far from the mirror direction the lobe vanishes and eq 3.1.1 is (1 - F) rho_d / pi
    f = O.combined_brdf(deg(10.0), deg(70.0), 0.0, torch.tensor([0.5], dtype=DT), sig[:1], rho0[:1])
    beta, _ = O.microfacet_angles(deg(10.0), deg(70.0), 0.0)
    expect = (1 - O.schlick(rho0[:1], beta)) * 0.5 / math.pi
    torch.testing.assert_close(f, expect, rtol=0, atol=1e-5)
    # interpolation between the fitted wavelengths, constant outside
    s2, r0 = O.THESIS_SPECULAR.at(torch.tensor([400.0, 588.5, 2000.0], dtype=DT))
    torch.testing.assert_close(s2, torch.tensor([0.0313, 0.03025, 0.0146], dtype=DT))


def test_brdf_zero_below_horizon_and_devices(device):
    dt = torch.float32 if device.type == "mps" else DT
    ti = torch.tensor([0.3, 1.7], dtype=dt, device=device)
    f = O.combined_brdf(ti, torch.tensor(0.2, dtype=dt, device=device), math.pi, 0.5, 0.02, 0.04)
    assert f.device.type == device.type and float(f[1]) == 0.0 and float(f[0]) > 0


def test_local_angles_from_vectors_agree_with_the_cosines_from_angles():
    """``local_angles`` (unit vectors -> θi, θr, Δφ) and ``cosines_from_angles`` (angles -> cosines) are
    consistent: cos 2β from the angles is ω_i · ω_r, and the mirror direction has Δφ = π."""
    g = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=DT), dim=-1)
    s = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=DT), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=DT), dim=-1)
    ti, tr, dp = O.local_angles(n, s, v)
    ci, cr, c2b = O.cosines_from_angles(ti, tr, dp)
    torch.testing.assert_close(ci, (n * s).sum(-1), rtol=0, atol=1e-12)
    torch.testing.assert_close(cr, (n * v).sum(-1), rtol=0, atol=1e-12)
    torch.testing.assert_close(c2b, (s * v).sum(-1), rtol=0, atol=1e-12)
    mirror = 2 * (n * s).sum(-1, keepdim=True) * n - s
    torch.testing.assert_close(O.local_angles(n, s, mirror)[2], torch.full((500,), math.pi, dtype=DT), rtol=0,
                               atol=1e-6)
    torch.testing.assert_close(O.half_angle_cos(c2b), torch.cos(0.5 * torch.acos(c2b)), rtol=0, atol=1e-12)


def test_relative_azimuth_on_floats_numpy_and_tensors():
    """One formula, |φa − φb| folded to [0, 180] degrees, for floats, numpy arrays and tensors alike."""
    import numpy as np

    from torchskin.angles import relative_azimuth_deg

    a, b = [350.0, 20.0, -90.0, 10.0, 725.0], [10.0, 200.0, 90.0, 10.0, 0.0]
    want = [20.0, 180.0, 180.0, 0.0, 5.0]
    assert [relative_azimuth_deg(x, y) for x, y in zip(a, b)] == want
    assert relative_azimuth_deg(np.array(a), np.array(b)).tolist() == want
    assert relative_azimuth_deg(torch.tensor(a, dtype=DT), torch.tensor(b, dtype=DT)).tolist() == want


def test_shadowed_lobe_takes_a_python_number_sigma2():
    """``microfacet_brdf_cos(..., shadowing=True)`` with σ² as a Python number equals the tensor form (it raised
    TypeError in Smith's term before)."""
    ci, cr, c2b = torch.tensor([0.8, 0.3]), torch.tensor([0.7, 0.9]), torch.tensor([0.5, -0.2])
    a = O.microfacet_brdf_cos(ci, cr, c2b, 0.1, 0.04, shadowing=True)
    b = O.microfacet_brdf_cos(ci, cr, c2b, torch.tensor(0.1), 0.04, shadowing=True)
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert bool((a < O.microfacet_brdf_cos(ci, cr, c2b, 0.1, 0.04)).all())  # shadowing only removes light
