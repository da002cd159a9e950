"""Surface optics: Fresnel (eqs 2.2.4-2.2.6), Schlick (2.2.7), the Gaussian microfacet lobe (2.3.4-2.3.6),
the combined skin BRDF (3.1.1), observed reflectance (3.1.4) and DHR (2.3.2).

Angles are radians. ``theta_i``/``theta_r`` are measured from the (local) surface normal; ``delta_phi`` is the
relative azimuth with Δφ = π the forward (specular) plane, so the mirror direction is θr = θi, Δφ = π.
All functions broadcast their inputs and return on their device and dtype.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ._checks import as_tensor, check_range
from .bands import Band, as_bands

_EPS_COS = 1e-12
_HALF_PI = math.pi / 2 * (1 + 1e-6)  # π/2 with room for its float32 rounding (1.5707964 > π/2)


def _check_surface_params(sigma2=None, rho0=None, rho_d=None, r_sub=None) -> None:
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


def _check_numbers(**values) -> None:
    """``_check_surface_params`` for the arguments that are Python numbers (free: no tensor, no device sync)."""
    nums = {k: v for k, v in values.items() if isinstance(v, (int, float))}
    if nums:
        _check_surface_params(**nums)


# ------------------------------------------------------------------------------------------------ Fresnel
def fresnel_normal(n1, n2) -> torch.Tensor:
    """Normal-incidence reflectance ((n2 - n1) / (n2 + n1))^2, eq 2.2.4."""
    n1, n2 = torch.broadcast_tensors(as_tensor(n1), as_tensor(n2))
    return ((n2 - n1) / (n2 + n1)) ** 2


def _cos_t(theta_i, n1, n2):
    cos_i = torch.cos(theta_i)
    sin_t2 = (n1 / n2) ** 2 * (1 - cos_i**2)
    tir = sin_t2 >= 1
    cos_t = torch.sqrt(torch.clamp(1 - sin_t2, min=0.0))
    return cos_i, cos_t, tir


def fresnel_s(theta_i, n1=1.0, n2=1.5) -> torch.Tensor:
    """s-polarised reflectance, eq 2.2.5 (1 under total internal reflection)."""
    theta_i = as_tensor(theta_i)
    n1, n2 = as_tensor(n1, like=theta_i), as_tensor(n2, like=theta_i)
    cos_i, cos_t, tir = _cos_t(theta_i, n1, n2)
    r = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    return torch.where(tir, torch.ones_like(r), r)


def fresnel_p(theta_i, n1=1.0, n2=1.5) -> torch.Tensor:
    """p-polarised reflectance, eq 2.2.6 (1 under total internal reflection)."""
    theta_i = as_tensor(theta_i)
    n1, n2 = as_tensor(n1, like=theta_i), as_tensor(n2, like=theta_i)
    cos_i, cos_t, tir = _cos_t(theta_i, n1, n2)
    r = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return torch.where(tir, torch.ones_like(r), r)


def fresnel_unpolarized(theta_i, n1=1.0, n2=1.5) -> torch.Tensor:
    """Unpolarised reflectance: the mean of eqs 2.2.5 and 2.2.6."""
    return 0.5 * (fresnel_s(theta_i, n1, n2) + fresnel_p(theta_i, n1, n2))


def schlick(rho0, theta) -> torch.Tensor:
    """Schlick's approximation, eq 2.2.7: ρ0 + (1 - ρ0)(1 - cos θ)^5."""
    theta = as_tensor(theta)
    rho0 = as_tensor(rho0, like=theta)
    return schlick_cos(rho0, torch.cos(theta))


def schlick_cos(rho0, cos_theta):
    """Schlick's approximation from a cosine (tensors or floats): ρ0 + (1 - ρ0)(1 - cos θ)^5."""
    return rho0 + (1 - rho0) * (1 - cos_theta) ** 5


def rho0_to_n(rho0, n1: float = 1.0) -> torch.Tensor:
    """Refractive index from normal reflectance (eq 2.2.4 inverted): n = n1 (1 + √ρ0) / (1 - √ρ0)."""
    rho0 = as_tensor(rho0)
    check_range("rho0", rho0, 0.0, 0.999999)
    s = torch.sqrt(rho0)
    return n1 * (1 + s) / (1 - s)


def n_to_rho0(n, n1: float = 1.0) -> torch.Tensor:
    """Normal reflectance of the interface n1 -> n (eq 2.2.4)."""
    return fresnel_normal(n1, n)


# ----------------------------------------------------------------------------------------- microfacet lobe
def microfacet_angles(theta_i, theta_r, delta_phi) -> tuple[torch.Tensor, torch.Tensor]:
    """``(β, θ)`` of eqs 2.3.5-2.3.6: the incidence angle on the facet and the facet tilt from the normal."""
    theta_i, theta_r, delta_phi = torch.broadcast_tensors(
        as_tensor(theta_i), as_tensor(theta_r), as_tensor(delta_phi)
    )
    ci, cr = torch.cos(theta_i), torch.cos(theta_r)
    cos2b = ci * cr + torch.sin(theta_i) * torch.sin(theta_r) * torch.cos(delta_phi)
    # clamp away from ±1: acos has an infinite derivative there
    beta = 0.5 * torch.acos(cos2b.clamp(-1 + 1e-12, 1 - 1e-12))
    cos_t = (ci + cr) / (2 * torch.cos(beta)).clamp_min(_EPS_COS)
    theta = torch.acos(cos_t.clamp(-1 + 1e-12, 1 - 1e-12))
    return beta, theta


def _smith_g1(cos_v, m2):
    """Smith masking for a Beckmann distribution with slope variance m² (exact erf form), from cos θ."""
    c = cos_v.clamp(1e-12, 1.0)
    a = c / (torch.sqrt(m2) * torch.sqrt((1 - c * c).clamp_min(1e-24)))  # 1 / (m tan θ)
    lam = 0.5 * (torch.erf(a) - 1) + torch.exp(-a * a) / (2 * a * math.sqrt(math.pi))
    return 1.0 / (1.0 + lam)


def microfacet_brdf_cos(cos_i, cos_r, cos_2beta, sigma2, rho0, *, shadowing: bool = False) -> torch.Tensor:
    """Eq 2.3.4 from cosines: cos θi, cos θr and cos 2β = ω_i · ω_r (the angle between the directions to
    the source and to the viewer). The vector form used by the renderer; see ``microfacet_brdf``. Tensor
    parameters are not validated here (no device synchronisation on the hot path)."""
    _check_numbers(sigma2=sigma2, rho0=rho0)
    cos_b = torch.sqrt((0.5 * (1 + cos_2beta)).clamp(1e-24, 1.0))
    ct = ((cos_i + cos_r) / (2 * cos_b)).clamp(-1.0, 1.0)  # cos of the facet tilt θ, eq 2.3.6
    ct2 = (ct * ct).clamp_min(_EPS_COS)
    tan2 = (1 - ct2) / ct2
    fresnel = schlick_cos(rho0, cos_b)  # Schlick at the facet incidence β
    f = fresnel * torch.exp(-tan2 / (2 * sigma2)) / (
        8 * math.pi * sigma2 * (ct2 * ct2) * (cos_i * cos_r).clamp_min(_EPS_COS))
    if shadowing:
        m2 = 2 * sigma2
        f = f * _smith_g1(cos_i, m2) * _smith_g1(cos_r, m2)
    return torch.where((cos_i > 0) & (cos_r > 0), f, torch.zeros_like(f))


def microfacet_brdf(theta_i, theta_r, delta_phi, sigma2, rho0, *, shadowing: bool = False) -> torch.Tensor:
    """Gaussian microfacet specular lobe, eq 2.3.4 (sr^-1).

    Cook-Torrance with a Beckmann distribution of slope variance m² = 2σ² and Schlick Fresnel at the facet
    incidence β; no shadowing by default (the thesis's form). ``shadowing=True`` multiplies by the separable
    Smith masking-shadowing G = G1(θi) G1(θr), which keeps the lobe energy-bounded at grazing angles.
    Returns 0 for directions below the horizon. ``sigma2`` must be > 0 (finite), ``rho0`` in [0, 1).
    """
    theta_i, theta_r, delta_phi = torch.broadcast_tensors(as_tensor(theta_i), as_tensor(theta_r),
                                                          as_tensor(delta_phi))
    ci, cr = torch.cos(theta_i), torch.cos(theta_r)
    cos2b = ci * cr + torch.sin(theta_i) * torch.sin(theta_r) * torch.cos(delta_phi)  # eq 2.3.5
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

    wavelengths_nm: tuple[float, ...] = (544.0, 633.0, 1080.0, 1580.0)
    sigma2: tuple[float, ...] = (0.0313, 0.0292, 0.0214, 0.0146)
    rho0: tuple[float, ...] = (0.030, 0.038, 0.045, 0.042)

    def at(self, wavelengths) -> tuple[torch.Tensor, torch.Tensor]:
        """``(σ², ρ0)`` at ``wavelengths`` (nm), on their device and dtype."""
        from .data import interp

        wl = as_tensor(wavelengths)
        xp = torch.tensor(self.wavelengths_nm, dtype=wl.dtype, device=wl.device)
        fp = torch.tensor([self.sigma2, self.rho0], dtype=wl.dtype, device=wl.device)
        out = interp(wl.clamp(xp[0], xp[-1]), xp, fp)
        return out[0], out[1]

    def for_bands(self, bands: Sequence[Band] | None = None, dtype=None, device=None):
        bands = as_bands(bands)
        wl = torch.tensor([b.center_nm for b in bands], dtype=dtype or torch.get_default_dtype(), device=device)
        return self.at(wl)


THESIS_SPECULAR = SpecularParams()


def combined_brdf_cos(cos_i, cos_r, cos_2beta, rho_d, sigma2, rho0, *, shadowing: bool = False) -> torch.Tensor:
    """Eq 3.1.1 from cosines (see ``microfacet_brdf_cos``); the renderer's form of ``combined_brdf``."""
    _check_numbers(rho_d=rho_d)
    fs = microfacet_brdf_cos(cos_i, cos_r, cos_2beta, sigma2, rho0, shadowing=shadowing)
    cos_b = torch.sqrt((0.5 * (1 + cos_2beta)).clamp(1e-24, 1.0))
    fd = (1 - schlick_cos(rho0, cos_b)) * rho_d / math.pi
    return fs + torch.where((cos_i > 0) & (cos_r > 0), fd, torch.zeros_like(fd))


def combined_brdf(theta_i, theta_r, delta_phi, rho_d, sigma2, rho0, *, shadowing: bool = False) -> torch.Tensor:
    """Combined skin BRDF, eq 3.1.1: f_s + (1 - ρ_Schlick(ρ0, β)) ρ_d / π (sr^-1).

    ``rho_d`` is the diffuse (subsurface) reflectance, e.g. ``tissue.diffuse_reflectance`` at the local
    incidence; all inputs broadcast, the band axis last. ``rho_d`` must lie in [0, 1], ``sigma2`` > 0
    (finite), ``rho0`` in [0, 1).
    """
    theta_i, theta_r, delta_phi = torch.broadcast_tensors(as_tensor(theta_i), as_tensor(theta_r),
                                                          as_tensor(delta_phi))
    ci, cr = torch.cos(theta_i), torch.cos(theta_r)
    cos2b = ci * cr + torch.sin(theta_i) * torch.sin(theta_r) * torch.cos(delta_phi)
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


def skin_diffuse(r_sub, r0, front=1.0):
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


def skin_brdf_cos(cos_i, cos_r, cos_2beta, r_sub, sigma2, rho0, front=1.0, *, shadowing: bool = False):
    """The combined skin BRDF of eq 3.1.1 from cosines, with ρ_d from ``skin_diffuse`` at R0 = Schlick(ρ0, θi)
    (``front``: 1 thesis, 0 conserving). All inputs broadcast, band axis last; sr^-1."""
    _check_numbers(r_sub=r_sub)
    rho_d = skin_diffuse(r_sub, schlick_cos(rho0, cos_i.clamp(0.0, 1.0)), front)
    return combined_brdf_cos(cos_i, cos_r, cos_2beta, rho_d, sigma2, rho0, shadowing=shadowing)


def skin_brdf(theta_i, theta_r, delta_phi, r_sub, sigma2, rho0, surface: str = DEFAULT_SURFACE, *,
              shadowing: bool = False) -> torch.Tensor:
    """The combined skin BRDF of eq 3.1.1 (sr^-1) from the subsurface reflectance ``r_sub``: the specular lobe
    (eq 2.3.4) plus (1 - ρ_Schlick(β)) ρ_d / π with ρ_d from the skin surface model ``surface`` ("thesis" or
    "conserving", see ``skin_diffuse``). Angles in radians (Δφ = π forward); inputs broadcast, band axis last.
    ``r_sub`` must lie in [0, 1], ``sigma2`` > 0 (finite), ``rho0`` in [0, 1)."""
    front = surface_front(surface)
    theta_i, theta_r, delta_phi = torch.broadcast_tensors(as_tensor(theta_i), as_tensor(theta_r),
                                                          as_tensor(delta_phi))
    ci, cr = torch.cos(theta_i), torch.cos(theta_r)
    cos2b = ci * cr + torch.sin(theta_i) * torch.sin(theta_r) * torch.cos(delta_phi)
    r_sub, sigma2, rho0 = (as_tensor(x, like=ci) for x in (r_sub, sigma2, rho0))
    _check_surface_params(sigma2=sigma2, rho0=rho0, r_sub=r_sub)
    return skin_brdf_cos(ci, cr, cos2b, r_sub, sigma2, rho0, front, shadowing=shadowing)


def observed_reflectance(brdf, theta_r, solid_angle) -> torch.Tensor:
    """Reflectance seen by a detector of solid angle Ω = A_optic / R², eq 3.1.4: f · Ω · cos θr."""
    brdf = as_tensor(brdf)
    return brdf * as_tensor(solid_angle, like=brdf) * torch.cos(as_tensor(theta_r, like=brdf))


def gauss_legendre(n: int, a: float, b: float, dtype=torch.float64, device=None):
    """Nodes and weights of n-point Gauss-Legendre quadrature on [a, b] (Golub-Welsch, in torch)."""
    k = torch.arange(1, n, dtype=torch.float64)
    off = k / torch.sqrt(4 * k * k - 1)
    jac = torch.diag(off, 1) + torch.diag(off, -1)
    x, v = torch.linalg.eigh(jac)
    w = 2 * v[0] ** 2
    x = 0.5 * (b - a) * x + 0.5 * (b + a)
    w = 0.5 * (b - a) * w
    return x.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device)


def dhr(brdf_fn, theta_i, n_theta: int = 96, n_phi: int = 128) -> torch.Tensor:
    """Directional-hemispherical reflectance, eq 2.3.2, by quadrature.

    ``brdf_fn(theta_i, theta_r, delta_phi)`` receives tensors broadcasting to ``S + (n_theta, n_phi)``, where
    S is ``theta_i``'s shape, and returns the BRDF there (parameters inside it must broadcast the same way,
    e.g. per-band values shaped ``(B, 1, 1)`` with ``theta_i`` of shape ``(B,)``). Returns shape S.
    Gauss-Legendre in θr, the periodic trapezoid rule in Δφ. ``theta_i`` must lie in [0, π/2].
    """
    theta_i = as_tensor(theta_i)
    check_range("theta_i", theta_i, 0.0, _HALF_PI, "rad")
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


def spectralon_brdf_cos(cos_i, cos_r, cos_2beta, rho, wavelength_nm) -> torch.Tensor:
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
