"""The renderer's ELM stage (``render.elm``, eqs 2.5.4-2.5.7) and BRDF-ELM (eqs 3.3.1-3.3.3) on analytic cases."""

import math

import pytest
import torch

from torchskin import optics as O
from torchskin.render import elm as C

DT = torch.float64


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


def test_panel_subset_is_a_regular_capped_sample_spread_over_the_panel():
    from torchskin.render.elm import panel_subset

    ix = torch.arange(1000, 4600, 3)  # 1,200 sorted flat indices of one panel
    (sub,), = panel_subset([[ix]], 256)
    assert 128 < sub.numel() <= 256 and bool(torch.isin(sub, ix).all())
    assert int(sub[0]) == int(ix[0]) and int(ix[-1]) - int(sub[-1]) < 5 * 3  # first to (nearly) last: whole panel
    steps = sub.diff()
    assert bool((steps == steps[0]).all())  # every k-th
    (same,), = panel_subset([[ix[:100]]], 256)
    assert torch.equal(same, ix[:100])  # under the cap: all of them
    with pytest.raises(ValueError, match="cap"):
        panel_subset([[ix]], 0)
