"""Surface optics: Fresnel (eqs 2.2.4-2.2.6), Schlick (2.2.7), the Gaussian microfacet lobe (2.3.4-2.3.6),
the combined skin BRDF (3.1.1), observed reflectance (3.1.4) and DHR (2.3.2).

Angles are radians. ``theta_i``/``theta_r`` are measured from the (local) surface normal; ``delta_phi`` is the
relative azimuth with Δφ = π the forward (specular) plane, so the mirror direction is θr = θi, Δφ = π.
All functions broadcast their inputs and return on their device and dtype.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import overload

import torch

from ._checks import Numeric, TensorLike, as_tensor, check_range
from .bands import INDEX_BANDS_NM, Band, as_bands

_EPS_COS = 1e-12
#: the largest accepted incidence angle, rad: π/2 with room for its float32 rounding (1.5707964 > π/2)
MAX_INCIDENCE_RAD = math.pi / 2 * (1 + 1e-6)


def _check_surface_params(sigma2: TensorLike | None = None, rho0: TensorLike | None = None,
                          rho_d: TensorLike | None = None, r_sub: TensorLike | None = None) -> None:
    """Validate the material parameters of the public BRDFs (σ² > 0 finite, ρ0 in [0, 1), ρ_d and R_sub in
    [0, 1]); the ``*_cos`` kernels, the renderer's per-frame path, skip this (see ``_check_numbers``)."""
    if sigma2 is not None:
        check_range("sigma2", sigma2, 0.0, math.inf, lo_open=True, hi_open=True)
    if rho0 is not None:
        check_range("rho0", rho0, 0.0, 1.0, hi_open=True)
    if rho_d is not None:
        check_range("rho_d", rho_d, 0.0, 1.0)
    if r_sub is not None:
        check_range("r_sub", r_sub, 0.0, 1.0)


def _check_numbers(**values: TensorLike) -> None:
    """``_check_surface_params`` for the arguments that are Python numbers (free: no tensor, no device sync)."""
    nums = {k: v for k, v in values.items() if isinstance(v, (int, float))}
    if nums:
        _check_surface_params(**nums)


# ------------------------------------------------------------------------------------------------ Fresnel
def fresnel_normal(n1: TensorLike, n2: TensorLike) -> torch.Tensor:
    """Normal-incidence reflectance ((n2 - n1) / (n2 + n1))^2, eq 2.2.4."""
    a, b = torch.broadcast_tensors(as_tensor(n1), as_tensor(n2))
    return ((b - a) / (b + a)) ** 2


def _cos_t(theta_i: torch.Tensor, n1: torch.Tensor,
           n2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    cos_i = torch.cos(theta_i)
    sin_t2 = (n1 / n2) ** 2 * (1 - cos_i**2)
    tir = sin_t2 >= 1
    cos_t = torch.sqrt(torch.clamp(1 - sin_t2, min=0.0))
    return cos_i, cos_t, tir


def fresnel_s(theta_i: TensorLike, n1: TensorLike = 1.0, n2: TensorLike = 1.5) -> torch.Tensor:
    """s-polarised reflectance, eq 2.2.5 (1 under total internal reflection)."""
    theta_i = as_tensor(theta_i)
    n1, n2 = as_tensor(n1, like=theta_i), as_tensor(n2, like=theta_i)
    cos_i, cos_t, tir = _cos_t(theta_i, n1, n2)
    r = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    return torch.where(tir, torch.ones_like(r), r)


def fresnel_p(theta_i: TensorLike, n1: TensorLike = 1.0, n2: TensorLike = 1.5) -> torch.Tensor:
    """p-polarised reflectance, eq 2.2.6 (1 under total internal reflection)."""
    theta_i = as_tensor(theta_i)
    n1, n2 = as_tensor(n1, like=theta_i), as_tensor(n2, like=theta_i)
    cos_i, cos_t, tir = _cos_t(theta_i, n1, n2)
    r = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return torch.where(tir, torch.ones_like(r), r)


def fresnel_unpolarized(theta_i: TensorLike, n1: TensorLike = 1.0, n2: TensorLike = 1.5) -> torch.Tensor:
    """Unpolarised reflectance: the mean of eqs 2.2.5 and 2.2.6."""
    return 0.5 * (fresnel_s(theta_i, n1, n2) + fresnel_p(theta_i, n1, n2))


def schlick(rho0: TensorLike, theta: TensorLike) -> torch.Tensor:
    """Schlick's approximation of the Fresnel reflectance, eq 2.2.7: ρ0 + (1 - ρ0)(1 - cos θ)^5.

    Args:
        rho0: normal-incidence reflectance ρ0 (eq 2.2.4; 0.04 for n = 1.5).
        theta: incidence angle, rad.

    Shape:
        ``rho0`` and ``theta`` broadcast; the result has the broadcast shape, on ``theta``'s device and dtype.

    Returns:
        The reflectance, ρ0 at normal incidence rising to 1 at grazing incidence.

    >>> round(float(schlick(0.04, 0.0)), 4), round(float(schlick(0.04, math.radians(80.0))), 4)
    (0.04, 0.4099)
    """
    theta = as_tensor(theta)
    rho0 = as_tensor(rho0, like=theta)
    return schlick_cos(rho0, torch.cos(theta))


@overload
def schlick_cos(rho0: float, cos_theta: float) -> float: ...


@overload
def schlick_cos(rho0: Numeric, cos_theta: torch.Tensor) -> torch.Tensor: ...


@overload
def schlick_cos(rho0: torch.Tensor, cos_theta: Numeric) -> torch.Tensor: ...


def schlick_cos(rho0: Numeric, cos_theta: Numeric) -> Numeric:
    """Schlick's approximation from a cosine, eq 2.2.7: ρ0 + (1 - ρ0)(1 - cos θ)^5: the one place the formula
    is written (``schlick`` and every BRDF call it).

    Args:
        rho0: normal-incidence reflectance ρ0.
        cos_theta: cosine of the incidence angle.

    Shape:
        Tensors broadcast; floats give a float (no tensor is made).

    Returns:
        The reflectance, of the inputs' kind.

    >>> round(float(schlick_cos(0.04, 0.5)), 4), schlick_cos(0.04, 1.0)
    (0.07, 0.04)
    """
    return rho0 + (1 - rho0) * (1 - cos_theta) ** 5


def rho0_to_n(rho0: TensorLike, n1: float = 1.0) -> torch.Tensor:
    """Refractive index from normal reflectance (eq 2.2.4 inverted): n = n1 (1 + √ρ0) / (1 - √ρ0)."""
    rho0 = as_tensor(rho0)
    check_range("rho0", rho0, 0.0, 0.999999)
    s = torch.sqrt(rho0)
    return n1 * (1 + s) / (1 - s)


def n_to_rho0(n: TensorLike, n1: float = 1.0) -> torch.Tensor:
    """Normal reflectance of the interface n1 -> n (eq 2.2.4)."""
    return fresnel_normal(n1, n)


# ------------------------------------------------------------------------------------------- local angles
def cosines_from_angles(theta_i: TensorLike, theta_r: TensorLike,
                        delta_phi: TensorLike) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The cosines the ``*_cos`` BRDF kernels take, from local angles: cos θi, cos θr and
    cos 2β = cos θi cos θr + sin θi sin θr cos Δφ = ω_i · ω_r (eq 2.3.5).

    Args:
        theta_i: incidence angle from the local normal, rad.
        theta_r: view angle from the local normal, rad.
        delta_phi: relative azimuth, rad (Δφ = π the forward plane).

    Shape:
        The inputs broadcast together; the three outputs have the broadcast shape.

    Returns:
        ``(cos θi, cos θr, cos 2β)``.

    >>> ci, cr, c2b = cosines_from_angles(0.5, 0.5, math.pi)  # the mirror direction: 2β = θi + θr
    >>> round(float(c2b), 4), round(math.cos(1.0), 4)
    (0.5403, 0.5403)
    """
    ti, tr, dp = torch.broadcast_tensors(as_tensor(theta_i), as_tensor(theta_r), as_tensor(delta_phi))
    ci, cr = torch.cos(ti), torch.cos(tr)
    return ci, cr, ci * cr + torch.sin(ti) * torch.sin(tr) * torch.cos(dp)


def half_angle_cos(cos_2beta: torch.Tensor) -> torch.Tensor:
    """cos β from cos 2β = ω_i · ω_r: √((1 + cos 2β) / 2), with β the incidence angle on the facet that mirrors
    the source into the viewer (eq 2.3.5); clamped to [1e-12, 1] (finite at back-scatter, 2β = π).

    >>> round(float(half_angle_cos(torch.tensor(0.0))), 4)  # 2β = 90°: β = 45°
    0.7071
    """
    return torch.sqrt((0.5 * (1 + cos_2beta)).clamp(1e-24, 1.0))


def dot3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a·b over the last axis (3 components), written out in a fixed order: the same bits for any thread count
    or CPU, where ``(a * b).sum(-1)`` leaves the summation order to the reduction kernel.

    >>> float(dot3(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([4.0, 5.0, 6.0])))
    32.0
    """
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def local_angles(normal: torch.Tensor, to_source: torch.Tensor,
                 to_viewer: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Local angles ``(θi, θr, Δφ)`` in rad of a surface point from unit vectors: θi between the normal and the
    direction to the source, θr between the normal and the direction to the viewer, Δφ between the two
    directions projected on the tangent plane (Δφ = π: the forward, specular plane; π/2 where a projection
    vanishes).

    Args:
        normal: unit surface normals.
        to_source: unit directions from the surface to the source.
        to_viewer: unit directions from the surface to the viewer.

    Shape:
        ``(..., 3)`` each, broadcasting together; the outputs have the broadcast batch shape ``(...)``.

    Returns:
        ``(theta_i, theta_r, delta_phi)``, rad.

    >>> n = torch.tensor([0.0, 0.0, 1.0])
    >>> s, v = torch.tensor([0.6, 0.0, 0.8]), torch.tensor([-0.6, 0.0, 0.8])
    >>> [round(math.degrees(float(a)), 2) for a in local_angles(n, s, v)]
    [36.87, 36.87, 180.0]
    """
    ci = dot3(normal, to_source).clamp(-1, 1)
    cr = dot3(normal, to_viewer).clamp(-1, 1)
    st, vt = to_source - ci[..., None] * normal, to_viewer - cr[..., None] * normal
    cphi = (dot3(st, vt) / (dot3(st, st) * dot3(vt, vt)).sqrt().clamp_min(1e-12)).clamp(-1, 1)
    return torch.acos(ci), torch.acos(cr), torch.acos(cphi)


# ----------------------------------------------------------------------------------------- microfacet lobe


def microfacet_angles(theta_i: TensorLike, theta_r: TensorLike,
                      delta_phi: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
    """``(β, θ)`` of eqs 2.3.5-2.3.6: the incidence angle on the facet and the facet tilt from the normal."""
    ci, cr, cos2b = cosines_from_angles(theta_i, theta_r, delta_phi)
    # clamp away from ±1: acos has an infinite derivative there
    beta = 0.5 * torch.acos(cos2b.clamp(-1 + 1e-12, 1 - 1e-12))
    cos_t = (ci + cr) / (2 * torch.cos(beta)).clamp_min(_EPS_COS)
    theta = torch.acos(cos_t.clamp(-1 + 1e-12, 1 - 1e-12))
    return beta, theta


def _smith_g1(cos_v: torch.Tensor, m2: torch.Tensor) -> torch.Tensor:
    """Smith masking for a Beckmann distribution with slope variance m² (exact erf form), from cos θ."""
    c = cos_v.clamp(1e-12, 1.0)
    a = c / (torch.sqrt(m2) * torch.sqrt((1 - c * c).clamp_min(1e-24)))  # 1 / (m tan θ)
    lam = 0.5 * (torch.erf(a) - 1) + torch.exp(-a * a) / (2 * a * math.sqrt(math.pi))
    return 1.0 / (1.0 + lam)


def microfacet_brdf_cos(cos_i: torch.Tensor, cos_r: torch.Tensor, cos_2beta: torch.Tensor, sigma2: Numeric,
                        rho0: Numeric, *, shadowing: bool = False) -> torch.Tensor:
    """Eq 2.3.4 from cosines: cos θi, cos θr and cos 2β = ω_i · ω_r (the angle between the directions to
    the source and to the viewer). The vector form used by the renderer; see ``microfacet_brdf``. Tensor
    parameters are not validated here (no device synchronisation on the hot path)."""
    _check_numbers(sigma2=sigma2, rho0=rho0)
    cos_b = half_angle_cos(cos_2beta)
    ct = ((cos_i + cos_r) / (2 * cos_b)).clamp(-1.0, 1.0)  # cos of the facet tilt θ, eq 2.3.6
    ct2 = (ct * ct).clamp_min(_EPS_COS)
    tan2 = (1 - ct2) / ct2
    fresnel = schlick_cos(rho0, cos_b)  # Schlick at the facet incidence β
    f = fresnel * torch.exp(-tan2 / (2 * sigma2)) / (
        8 * math.pi * sigma2 * (ct2 * ct2) * (cos_i * cos_r).clamp_min(_EPS_COS))
    if shadowing:
        m2 = 2 * as_tensor(sigma2, like=cos_i)  # a Python-number sigma2 too (torch.sqrt takes tensors only)
        f = f * _smith_g1(cos_i, m2) * _smith_g1(cos_r, m2)
    return torch.where((cos_i > 0) & (cos_r > 0), f, torch.zeros_like(f))


def microfacet_brdf(theta_i: TensorLike, theta_r: TensorLike, delta_phi: TensorLike, sigma2: TensorLike,
                    rho0: TensorLike, *, shadowing: bool = False) -> torch.Tensor:
    """Gaussian microfacet specular lobe, eq 2.3.4 (sr^-1).

    Cook-Torrance with a Beckmann distribution of slope variance m² = 2σ² and Schlick Fresnel at the facet
    incidence β; no shadowing by default (the thesis's form).

    Args:
        theta_i, theta_r: incidence and view angles from the normal, rad.
        delta_phi: relative azimuth, rad (Δφ = π the forward plane).
        sigma2: slope parameter σ² (> 0, finite); the thesis's per band: ``THESIS_SPECULAR``.
        rho0: Schlick normal reflectance ρ0, in [0, 1).
        shadowing: multiply by the separable Smith masking-shadowing G = G1(θi) G1(θr), which keeps the lobe
            energy-bounded at grazing angles.

    Shape:
        All inputs broadcast (band axis last); the result has the broadcast shape.

    Returns:
        The BRDF in sr^-1; 0 for directions below the horizon.

    >>> round(float(microfacet_brdf(math.radians(30.0), math.radians(30.0), math.pi, 0.0146, 0.042)), 4)
    0.1528
    """
    ci, cr, cos2b = cosines_from_angles(theta_i, theta_r, delta_phi)
    sigma2, rho0 = as_tensor(sigma2, like=ci), as_tensor(rho0, like=ci)
    _check_surface_params(sigma2=sigma2, rho0=rho0)
    return microfacet_brdf_cos(ci, cr, cos2b, sigma2, rho0, shadowing=shadowing)


# ------------------------------------------------------------------------------ per-band specular defaults
@dataclass(frozen=True)
class SpecularParams:
    """Per-band microfacet parameters: slope variance σ² and Schlick normal reflectance ρ0.

    Defaults: the thesis's fits (section 3.3.3): CASI scatterometer at 544 and 633 nm, image fits at 1080 and
    1580 nm. Between the fitted wavelengths the parameters are interpolated linearly, outside held constant.
    """

    wavelengths_nm: tuple[float, ...] = INDEX_BANDS_NM
    sigma2: tuple[float, ...] = (0.0313, 0.0292, 0.0214, 0.0146)
    rho0: tuple[float, ...] = (0.030, 0.038, 0.045, 0.042)

    def at(self, wavelengths: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
        """``(σ², ρ0)`` at ``wavelengths`` (nm), on their device and dtype."""
        from .data import interp

        wl = as_tensor(wavelengths)
        xp = torch.tensor(self.wavelengths_nm, dtype=wl.dtype, device=wl.device)
        fp = torch.tensor([self.sigma2, self.rho0], dtype=wl.dtype, device=wl.device)
        out = interp(wl.clamp(xp[0], xp[-1]), xp, fp)
        return out[0], out[1]

    def for_bands(self, bands: Sequence[Band] | None = None, dtype: torch.dtype | None = None,
                  device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(σ², ρ0)`` at the centres of ``bands`` (default ``DEFAULT_BANDS``), each ``(n_bands,)``."""
        bands = as_bands(bands)
        wl = torch.tensor([b.center_nm for b in bands], dtype=dtype or torch.get_default_dtype(), device=device)
        return self.at(wl)


THESIS_SPECULAR = SpecularParams()


def combined_brdf_cos(cos_i: torch.Tensor, cos_r: torch.Tensor, cos_2beta: torch.Tensor, rho_d: Numeric,
                      sigma2: Numeric, rho0: Numeric, *, shadowing: bool = False) -> torch.Tensor:
    """Eq 3.1.1 from cosines (see ``microfacet_brdf_cos``); the renderer's form of ``combined_brdf``."""
    _check_numbers(rho_d=rho_d)
    fs = microfacet_brdf_cos(cos_i, cos_r, cos_2beta, sigma2, rho0, shadowing=shadowing)
    fd = (1 - schlick_cos(rho0, half_angle_cos(cos_2beta))) * rho_d / math.pi
    return fs + torch.where((cos_i > 0) & (cos_r > 0), fd, torch.zeros_like(fd))


def combined_brdf(theta_i: TensorLike, theta_r: TensorLike, delta_phi: TensorLike, rho_d: TensorLike,
                  sigma2: TensorLike, rho0: TensorLike, *, shadowing: bool = False) -> torch.Tensor:
    """Combined BRDF, eq 3.1.1: f_s + (1 - ρ_Schlick(ρ0, β)) ρ_d / π (sr^-1), with a given diffuse reflectance.

    Args:
        theta_i, theta_r: incidence and view angles from the normal, rad.
        delta_phi: relative azimuth, rad (Δφ = π the forward plane).
        rho_d: the diffuse reflectance ρ_d in [0, 1], e.g. ``tissue.diffuse_reflectance`` at the local
            incidence (``skin_brdf`` derives it from the subsurface reflectance).
        sigma2: slope parameter σ² of the lobe (> 0, finite).
        rho0: Schlick normal reflectance ρ0, in [0, 1).
        shadowing: Smith shadowing on the lobe (see ``microfacet_brdf``).

    Shape:
        All inputs broadcast (band axis last); the result has the broadcast shape.

    Returns:
        The BRDF in sr^-1; 0 for directions below the horizon.

    >>> round(float(combined_brdf(math.radians(30.0), math.radians(30.0), math.pi, 0.5, 0.0146, 0.042)), 4)
    0.3052
    """
    ci, cr, cos2b = cosines_from_angles(theta_i, theta_r, delta_phi)
    rho_d, sigma2, rho0 = (as_tensor(x, like=ci) for x in (rho_d, sigma2, rho0))
    _check_surface_params(sigma2=sigma2, rho0=rho0, rho_d=rho_d)
    return combined_brdf_cos(ci, cr, cos2b, rho_d, sigma2, rho0, shadowing=shadowing)


# ------------------------------------------------------------------------------------ skin surface models
#: how the front surface enters eq 3.1.1's diffuse term ρ_d (``skin_diffuse``); "thesis" is the default
SURFACE_MODELS = ("thesis", "conserving")
DEFAULT_SURFACE = "thesis"


def check_surface(surface: str) -> str:
    """``surface`` if it names a skin surface model (``SURFACE_MODELS``), else ``ValueError``."""
    if surface not in SURFACE_MODELS:
        raise ValueError(f"surface must be one of {', '.join(SURFACE_MODELS)} (skin surface model), got {surface!r}")
    return surface


def surface_front(surface: str) -> float:
    """The weight of the front-surface term R0 in ``skin_diffuse``: 1 for "thesis", 0 for "conserving"."""
    return 1.0 if check_surface(surface) == "thesis" else 0.0


def skin_diffuse(r_sub: torch.Tensor, r0: Numeric, front: Numeric = 1.0) -> torch.Tensor:
    """Eq 3.1.1's diffuse reflectance ρ_d(θi) of skin from its subsurface reflectance R_sub (the nine layers
    and substrate, ``tissue.subsurface_reflectance``) under a front surface of reflectance R0 = Schlick(ρ0, θi):

        ρ_d = front · R0 + (1 - R0)² R_sub / (1 - R0 R_sub)

    ``front = 1`` (``surface="thesis"``, the default): the thesis's ρ_d, the *total* diffuse-model reflectance,
    front surface included. The thesis says what ρ_d is: the diffuse component is "represented by subsurface
    reflectance through radiometer measurements" (section 3.1); "the measured spectrum is a sum of surface and
    subsurface components" and the Kubelka-Munk model is fitted to that combined reflectance (3.2.2); Fig 18
    varies R0 "from 0.04 to 1" inside the KM stack, whose accumulated reflectance starts from R0 (eq 2.4.12
    with R_0 as the first layer); and in its Blender simulation "the diffuse reflectance is set to the
    radiometer measured reflectance value" (4.2.1). This is the model that agrees with the thesis's measured
    images (Fig 32). It counts the front-surface reflection twice (once in ρ_d, once in the specular lobe),
    so eq 3.1.1 is not energy-conserving: its directional-hemispherical reflectance exceeds 1 towards grazing
    incidence (``optics.dhr``; README).

    ``front = 0`` (``surface="conserving"``): the subsurface part only, the light that crosses the surface,
    scatters inside and leaves again. With the specular lobe carrying the surface reflection this conserves
    energy (with Smith shadowing the DHR stays <= 1 at every incidence). It lowers the apparent 1580 nm
    reflectance of skin away from the glint from about 0.085 to 0.045.

    ``front`` may be a tensor (per material) broadcasting with the inputs.
    """
    return (1 - r0) ** 2 * r_sub / (1 - r0 * r_sub) + front * r0


def skin_brdf_cos(cos_i: torch.Tensor, cos_r: torch.Tensor, cos_2beta: torch.Tensor, r_sub: torch.Tensor,
                  sigma2: Numeric, rho0: Numeric, front: Numeric = 1.0, *,
                  shadowing: bool = False) -> torch.Tensor:
    """The combined skin BRDF of eq 3.1.1 from cosines, with ρ_d from ``skin_diffuse`` at R0 = Schlick(ρ0, θi)
    (``front``: 1 thesis, 0 conserving). All inputs broadcast, band axis last; sr^-1."""
    _check_numbers(r_sub=r_sub)
    rho_d = skin_diffuse(r_sub, schlick_cos(rho0, cos_i.clamp(0.0, 1.0)), front)
    return combined_brdf_cos(cos_i, cos_r, cos_2beta, rho_d, sigma2, rho0, shadowing=shadowing)


def skin_brdf(theta_i: TensorLike, theta_r: TensorLike, delta_phi: TensorLike, r_sub: TensorLike,
              sigma2: TensorLike, rho0: TensorLike, surface: str = DEFAULT_SURFACE, *,
              shadowing: bool = False) -> torch.Tensor:
    """The combined skin BRDF of eq 3.1.1 (sr^-1) from the subsurface reflectance: the specular lobe (eq
    2.3.4) plus (1 - ρ_Schlick(β)) ρ_d / π, with ρ_d from the skin surface model ``surface`` at
    R0 = Schlick(ρ0, θi) (``skin_diffuse``).

    Args:
        theta_i, theta_r: incidence and view angles from the normal, rad.
        delta_phi: relative azimuth, rad (Δφ = π the forward plane).
        r_sub: subsurface reflectance R_sub in [0, 1] (``tissue.subsurface_reflectance``).
        sigma2: slope parameter σ² of the lobe (> 0, finite); per band: ``THESIS_SPECULAR.for_bands()``.
        rho0: Schlick normal reflectance ρ0, in [0, 1).
        surface: "thesis" (default: ρ_d includes the front-surface reflection) or "conserving".
        shadowing: Smith shadowing on the lobe (see ``microfacet_brdf``).

    Shape:
        All inputs broadcast (band axis last); the result has the broadcast shape.

    Returns:
        The BRDF in sr^-1; 0 for directions below the horizon.

    >>> sigma2, rho0 = THESIS_SPECULAR.for_bands()  # (4,) each: 544, 633, 1080, 1580 nm
    >>> theta_i = torch.tensor([0.1, 0.3, 0.5])[:, None]
    >>> skin_brdf(theta_i, 0.0, 0.0, torch.tensor([0.28, 0.6, 0.5, 0.05]), sigma2, rho0).shape
    torch.Size([3, 4])
    >>> t = math.radians(30.0)
    >>> round(float(skin_brdf(t, t, math.pi, 0.05, 0.0146, 0.042)), 4)
    0.1796
    """
    front = surface_front(surface)
    ci, cr, cos2b = cosines_from_angles(theta_i, theta_r, delta_phi)
    r_sub, sigma2, rho0 = (as_tensor(x, like=ci) for x in (r_sub, sigma2, rho0))
    _check_surface_params(sigma2=sigma2, rho0=rho0, r_sub=r_sub)
    return skin_brdf_cos(ci, cr, cos2b, r_sub, sigma2, rho0, front, shadowing=shadowing)


def observed_reflectance(brdf: TensorLike, theta_r: TensorLike, solid_angle: TensorLike) -> torch.Tensor:
    """Reflectance seen by a detector of solid angle Ω = A_optic / R², eq 3.1.4: f · Ω · cos θr."""
    brdf = as_tensor(brdf)
    return brdf * as_tensor(solid_angle, like=brdf) * torch.cos(as_tensor(theta_r, like=brdf))


def gauss_legendre(n: int, a: float, b: float, dtype: torch.dtype = torch.float64,
                   device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes and weights of n-point Gauss-Legendre quadrature on [a, b] (Golub-Welsch, in torch)."""
    k = torch.arange(1, n, dtype=torch.float64)
    off = k / torch.sqrt(4 * k * k - 1)
    jac = torch.diag(off, 1) + torch.diag(off, -1)
    x, v = torch.linalg.eigh(jac)
    w = 2 * v[0] ** 2
    x = 0.5 * (b - a) * x + 0.5 * (b + a)
    w = 0.5 * (b - a) * w
    return x.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device)


def dhr(brdf_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor], theta_i: TensorLike,
        n_theta: int = 96, n_phi: int = 128) -> torch.Tensor:
    """Directional-hemispherical reflectance, eq 2.3.2, by quadrature.

    ``brdf_fn(theta_i, theta_r, delta_phi)`` receives tensors broadcasting to ``S + (n_theta, n_phi)``, where
    S is ``theta_i``'s shape, and returns the BRDF there (parameters inside it must broadcast the same way,
    e.g. per-band values shaped ``(B, 1, 1)`` with ``theta_i`` of shape ``(B,)``). Returns shape S.
    Gauss-Legendre in θr, the periodic trapezoid rule in Δφ. ``theta_i`` must lie in [0, π/2].
    """
    theta_i = as_tensor(theta_i)
    check_range("theta_i", theta_i, 0.0, MAX_INCIDENCE_RAD, "rad")
    if n_theta < 1 or n_phi < 1:
        raise ValueError(f"n_theta and n_phi must be >= 1, got {n_theta}, {n_phi}")
    tr, wt = gauss_legendre(n_theta, 0.0, math.pi / 2, dtype=theta_i.dtype, device=theta_i.device)
    phi = torch.arange(n_phi, dtype=theta_i.dtype, device=theta_i.device) * (2 * math.pi / n_phi)
    f = brdf_fn(theta_i[..., None, None], tr[:, None], phi[None, :])
    w = (wt * torch.cos(tr) * torch.sin(tr))[:, None] * (2 * math.pi / n_phi)
    return (f * w).sum(dim=(-2, -1))


# ------------------------------------------------------------------------------------ Spectralon-like panel
#: drop of a Spectralon panel's BRDF seen at θr = 0 when the illumination moves from 0 to 75 degrees: the
#: thesis's estimate from Appendix B (section 4.1.1): 4.1 % in the visible, 7.4 % in the NIR
SPECTRALON_DROP_75 = {"vis": 0.041, "nir": 0.074}
SPECTRALON_LOBE_SIGMA2 = 0.05


def _spectralon_k(wavelength_nm: torch.Tensor) -> torch.Tensor:
    """Lobe strength per band so that f(75°, 0°) / f(0°, 0°) - 1 equals the thesis's estimate exactly."""
    drop = torch.where(wavelength_nm < 900, SPECTRALON_DROP_75["vis"], SPECTRALON_DROP_75["nir"])
    c75 = torch.tensor(math.cos(math.radians(75.0)), dtype=wavelength_nm.dtype, device=wavelength_nm.device)
    one = torch.ones_like(c75)
    lobe75 = math.pi * microfacet_brdf_cos(c75, one, c75, torch.tensor(SPECTRALON_LOBE_SIGMA2, dtype=c75.dtype), one)
    return drop / (1 - lobe75)


def spectralon_brdf_cos(cos_i: torch.Tensor, cos_r: torch.Tensor, cos_2beta: torch.Tensor, rho: Numeric,
                        wavelength_nm: TensorLike) -> torch.Tensor:
    """A Spectralon-like reference panel: Lambertian at normal incidence, with a weak forward lobe that grows
    with incidence and takes its energy from the diffuse part (Appendix B's behaviour):

        f = ρ/π (1 - k g(θi)) + ρ k g(θi) D(θh) / (4 cos θi cos θr),   g = ((1 - cos θi)/(1 - cos 75°))²,

    with D a Beckmann lobe (σ² = 0.05, no Fresnel, so the lobe's hemispherical reflectance is ≈ 1) and k
    per band set so that the BRDF seen at θr = 0 falls by the thesis's 4.1 % (VIS) / 7.4 % (NIR) between 0°
    and 75° illumination. ``rho`` is the panel's DHR (Table 3); inputs broadcast, band axis last.
    """
    k = _spectralon_k(as_tensor(wavelength_nm, like=cos_i))
    g = ((1 - cos_i).clamp_min(0) / (1 - math.cos(math.radians(75.0)))) ** 2
    one = torch.ones_like(cos_i)
    lobe = microfacet_brdf_cos(cos_i, cos_r, cos_2beta, torch.tensor(SPECTRALON_LOBE_SIGMA2, dtype=cos_i.dtype,
                                                                     device=cos_i.device), one)
    f = rho / math.pi * (1 - k * g) + rho * k * g * lobe
    return torch.where((cos_i > 0) & (cos_r > 0), f, torch.zeros_like(f))
