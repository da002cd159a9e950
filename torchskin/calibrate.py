"""Empirical line method (eqs 2.5.4-2.5.7) and its BRDF form (eqs 3.3.1-3.3.3) as tensor functions.

Radiances/signals ``L`` and panel references broadcast; the band axis is last by convention. A panel pair
with equal references in some band is an error (the line is undefined there).
"""

from __future__ import annotations

import torch

from ._checks import as_tensor


def elm_coefficients(L1, L2, ref1, ref2) -> tuple[torch.Tensor, torch.Tensor]:
    """Gain and offset ``(a, b)`` of L = a·ρ + b from two panels (eqs 2.5.5-2.5.6).

    ``L1``, ``L2``: measured signals of panels 1 and 2; ``ref1``, ``ref2``: their known reflectances (or,
    for BRDF-ELM, their BRDF values at the scene geometry).
    """
    L1 = as_tensor(L1)
    L2, ref1, ref2 = (as_tensor(x, like=L1) for x in (L2, ref1, ref2))
    dref = ref2 - ref1
    if bool((dref == 0).any()):
        raise ValueError("ref1 and ref2 must differ in every band (the empirical line is undefined otherwise)")
    a = (L2 - L1) / dref
    b = (L1 * ref2 - L2 * ref1) / dref
    return a, b


def elm_apply(L, a, b) -> torch.Tensor:
    """Map signals to reflectance, eq 2.5.7: ρ = (L - b) / a."""
    L = as_tensor(L)
    return (L - as_tensor(b, like=L)) / as_tensor(a, like=L)


def elm(L, L1, L2, ref1, ref2) -> torch.Tensor:
    """One-call ELM: coefficients from two panels, then applied to ``L``."""
    a, b = elm_coefficients(L1, L2, ref1, ref2)
    return elm_apply(L, a, b)


def brdf_elm(L, L1, L2, f1, f2, f_to_reflectance=None) -> torch.Tensor:
    """BRDF-ELM, eqs 3.3.1-3.3.3: the line L = a·f_BRDF + b through the panels' BRDF values ``f1``, ``f2``
    (sr^-1, at each pixel's source/view geometry) instead of their hemispherical reflectances.

    Returns the scene's BRDF (sr^-1), or, with ``f_to_reflectance`` (e.g. π for a Lambertian-equivalent
    reflectance, or Ω·cos θr for eq 3.1.4's observed reflectance), that factor times it.
    """
    f = elm(L, L1, L2, f1, f2)
    return f if f_to_reflectance is None else f * as_tensor(f_to_reflectance, like=f)
