"""Indices, rules detector, Bhattacharyya coefficient and the empirical line method."""

import math

import pytest
import torch

from torchskin import detect as D
from torchskin import optics as O
from torchskin.bands import Band
from torchskin.render import elm as C

DT = torch.float64


def test_index_signs_follow_design():
    # skin is redder than green and brighter at 1080 than at 1580: both indices as in the box's signs
    R = torch.tensor([0.3, 0.6, 0.6, 0.1], dtype=DT)
    g, s = D.indices(R)
    assert abs(float(g) - (0.3 - 0.6) / 0.9) < 1e-15 and float(g) < 0
    assert abs(float(s) - 0.5 / 0.7) < 1e-15 and float(s) > 0


def test_indices_find_bands_by_centre_and_axis():
    cube = torch.rand(2, 4, 5, 6, dtype=DT)  # (batch, bands, H, W)
    bands = [Band(1580), Band(544), Band(1080), Band(633)]
    g, s = D.indices(cube, bands, band_dim=1)
    torch.testing.assert_close(g, D.ndgri(cube[:, 1], cube[:, 3]))
    torch.testing.assert_close(s, D.ndsi(cube[:, 2], cube[:, 0]))
    with pytest.raises(ValueError, match="no band within"):
        D.indices(torch.rand(4), [Band(450), Band(633), Band(1080), Band(1580)])
    with pytest.raises(ValueError, match="3 bands"):
        D.indices(torch.rand(3))


def test_rules_detector_box_edges_and_tensor_box():
    b = D.DEFAULT_BOX
    g = torch.tensor([b.b1, b.b2, b.b1 - 1e-9, -0.3, -0.3, float("nan")], dtype=DT)
    s = torch.tensor([b.c1, b.c2, 0.7, b.c2 + 1e-9, 0.7, 0.7], dtype=DT)
    assert D.rules_detector(g, s).tolist() == [True, True, False, False, True, False]
    box = torch.tensor([b.b1, b.b2, b.c1, b.c2], dtype=DT)
    assert torch.equal(D.rules_detector(g, s, box), D.rules_detector(g, s))
    per_pixel = box.expand(6, 4).clone()
    per_pixel[4, 1] = -0.4  # tighten one pixel's box: it drops out
    assert D.rules_detector(g, s, per_pixel).tolist() == [True, True, False, False, False, False]
    with pytest.raises(ValueError, match="b1 <= b2"):
        D.RulesBox(b1=0.1, b2=-0.1)


def test_bhattacharyya_limits_and_symmetry():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(20000, generator=g, dtype=DT) * 0.1
    y = torch.randn(20000, generator=g, dtype=DT) * 0.1
    h = D.histogram2d(x, y, 32, (-1, 1), (-1, 1))
    assert float(h.sum()) == 20000
    assert abs(float(D.bhattacharyya(h, h)) - 1) < 1e-12
    h2 = D.histogram2d(x + 0.5, y, 32, (-1, 1), (-1, 1))
    bc = D.bhattacharyya(h, h2)
    assert abs(float(bc) - float(D.bhattacharyya(h2, h))) < 1e-15
    # two Gaussians of sigma 0.1 shifted by 0.5: BC = exp(-d^2 / (8 sigma^2)) = exp(-3.125)
    assert abs(float(bc) - math.exp(-0.5**2 / (8 * 0.1**2))) < 0.01
    near = D.histogram2d(x, y, 32, (-1, 7), (-1, 1))
    far = D.histogram2d(x + 5, y, 32, (-1, 7), (-1, 1))
    assert float(D.bhattacharyya(near, far)) == 0.0
    with pytest.raises(ValueError, match="empty"):
        D.bhattacharyya(torch.zeros(3, 3), torch.ones(3, 3))


def elm(L, L1, L2, ref1, ref2):
    """ELM through ``render.elm``: the line through two panels (signals ``L1``, ``L2``; references ``ref1``, ``ref2``),
    applied to ``L`` as the renderer applies it (``apply_elm`` on (S, C, H, W, B) frames)."""
    L, L1, L2, ref1, ref2 = (torch.as_tensor(x, dtype=DT) for x in (L, L1, L2, ref1, ref2))
    shape = torch.broadcast_shapes(L.shape, L1.shape)
    frame = L.expand(shape).reshape(1, 1, 1, -1, shape[-1] if len(shape) else 1)
    panels = torch.stack([L1.reshape(-1), L2.reshape(-1)])[None, None]  # (S, C, P, B)
    refs = torch.stack([ref1.expand(L1.shape).reshape(-1), ref2.expand(L1.shape).reshape(-1)])[None, None]
    return C.apply_elm(frame, panels, refs).reshape(shape)


def test_elm_recovers_reflectance_of_a_linear_sensor():
    g = torch.Generator().manual_seed(3)
    gain = torch.rand(4, generator=g, dtype=DT) * 100 + 10
    offset = torch.rand(4, generator=g, dtype=DT) * 5
    rho = torch.rand(100, 4, generator=g, dtype=DT)
    L = gain * rho + offset
    ref1, ref2 = torch.full((4,), 0.97, dtype=DT), torch.full((4,), 0.03, dtype=DT)
    a, b = C.elm_coefficients(gain * ref1 + offset, gain * ref2 + offset, ref1, ref2)
    torch.testing.assert_close(a, gain)
    torch.testing.assert_close(b, offset)
    torch.testing.assert_close(elm(L, gain * ref1 + offset, gain * ref2 + offset, ref1, ref2), rho)
    with pytest.raises(ValueError, match="differ"):
        C.elm_coefficients(L[0], L[1], ref1, ref1)


def test_appendix_c_panels_map_middle_panel_to_040():
    """Appendix C: Lambertian panels 0.97 and 0.02 with a 0.40 panel between, source and camera normal,
    a path radiance offset: ELM gives 0.40 for the middle panel."""
    E, tau, La = 1000.0, 0.9, 3.0
    radiance = lambda rho: tau * rho / math.pi * E + La  # noqa: E731 (eq 2.5.1)
    est = elm(radiance(0.40), radiance(0.97), radiance(0.02), 0.97, 0.02)
    assert abs(float(est) - 0.40) < 1e-6


def test_brdf_elm_corrects_a_specular_panel_where_dhr_elm_fails():
    """Eqs 3.3.1-3.3.3: with glossy panels seen near the mirror, ELM on the panels' DHR is biased; BRDF-ELM
    on their BRDF at the geometry recovers the target exactly."""
    ti, tr, dp = torch.tensor(0.9, dtype=DT), torch.tensor(0.9, dtype=DT), torch.tensor(math.pi, dtype=DT)
    E = 500.0

    def panel_brdf(rho):
        return rho / math.pi + O.microfacet_brdf(ti, tr, dp, 0.05, 0.04)

    f_target = torch.tensor(0.25 / math.pi, dtype=DT)  # a Lambertian target
    L = lambda f: f * E * torch.cos(ti) + 2.0  # noqa: E731
    f1, f2 = panel_brdf(0.97), panel_brdf(0.03)
    rho_brdf = math.pi * elm(L(f_target), L(f1), L(f2), f1, f2)  # BRDF-ELM: the line through the panels' BRDF
    rho_dhr = elm(L(f_target), L(f1), L(f2), 0.97, 0.03)
    assert abs(float(rho_brdf) - 0.25) < 1e-12
    assert abs(float(rho_dhr) - 0.25) > 0.01
