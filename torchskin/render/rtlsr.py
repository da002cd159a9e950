"""The kernel-driven Ross-Thick / Li-Sparse-Reciprocal (RTLSR) BRDF of the MODIS BRDF/albedo product, and the
per-band kernel weights of Roy et al. (2016) for the "rtlsr" material kind (``render.materials``).

The reflectance factor (dimensionless) is

    R(θi, θv, φ) = f_iso + f_vol K_vol + f_geo K_geo,      BRDF = R / π  (sr^-1),

with the RossThick volume-scattering kernel K_vol and the LiSparse-Reciprocal geometric-optical kernel K_geo
(h/b = 2, b/r = 1, so θ' = θ), as in Lucht, Schaaf & Strahler (2000), "An algorithm for the retrieval of albedo
from space using semiempirical BRDF models", IEEE TGRS 38(2):977-998, and Wanner, Li & Strahler (1995), JGR
100(D10):21077-21089. Both kernels are written from the three cosines the renderer has (cos θi, cos θv and
cos ξ = ω_i·ω_v, the cosine of the phase angle), never dividing by a sine.

Numerical guards: cos θi and cos θv are clamped to at least ``COS_MIN`` (θ <= 89.94°, where the kernels' sec θ
terms are 1000); the clamped values stay finite (and the BRDF is 0 where either cosine is <= 0). The kernel
model's R can go negative at extreme geometries (large negative K_geo near grazing): R is clamped at 0, which
adds 0.3-0.9 % to the model's white-sky albedo with the Roy et al. shape (the material's ``albedo`` stays ρ). Near
the hotspot (cos ξ -> 1) K_geo depends on sqrt(1 - cos ξ), so its precision there is limited to about 1e-8 by
the rounding of cos ξ itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

#: the LiSparse kernel's relative crown height h/b (MODIS: 2; its crown shape b/r = 1, so θ' = θ throughout)
HB = 2.0
#: the least cos θi, cos θv the kernels use (θ <= 89.94°): keeps sec θ, tan θ finite at and beyond the horizon
COS_MIN = 1e-3
#: white-sky (bi-hemispherical) albedo of K_vol and K_geo, Lucht et al. (2000) Table 1: the white-sky albedo
#: of R is f_iso + WSA_VOL f_vol + WSA_GEO f_geo
WSA_VOL = 0.189184
WSA_GEO = -1.377622

#: Roy et al. (2016), "A general method to normalize Landsat reflectance data to nadir BRDF adjusted
#: reflectance", Remote Sensing of Environment 176:255-271, Table 1: global MODIS-derived constant RTLSR
#: parameters per Landsat band, as {band: (OLI band centre nm, f_iso, f_geo, f_vol)} (the paper's order).
ROY2016: dict[str, tuple[float, float, float, float]] = {
    "blue": (482.0, 0.0774, 0.0079, 0.0372),
    "green": (561.0, 0.1306, 0.0178, 0.0580),
    "red": (655.0, 0.1690, 0.0227, 0.0574),
    "nir": (865.0, 0.3093, 0.0330, 0.1535),
    "swir1": (1609.0, 0.3430, 0.0453, 0.1154),
    "swir2": (2201.0, 0.2658, 0.0387, 0.0639),
}
#: the kernel-weight tables a material may name (``Material.params["kernels"]``)
KERNEL_TABLES = {"roy2016": ROY2016}
DEFAULT_KERNELS = "roy2016"

#: the illumination zeniths over which an "rtlsr" material's black-sky albedo must stay <= 1: [0, this], degrees.
#: Kernel-driven BRDFs are fitted and trusted to solar zeniths of about 70-80° (MODIS BRDF/albedo inversions);
#: beyond, with R clamped at 0, LiSparse-R's backscatter lobe (½ (1 + cos ξ) sec θi sec θv) is no longer offset by
#: its negative forward part and DHR / ρ grows like sec θi (largest DHR / ρ up to θi = 80°: 1.290; 85°: 1.428;
#: 88°: 2.159; 89°: 3.822). Under a sun lower than this an "rtlsr" surface may reflect more than it receives;
#: its radiance there is small (cos θi < 0.17) and the index bands' ratios, not energy, drive detection.
DHR_ZENITH_MAX_DEG = 80.0
#: the largest white-sky albedo (``reflectance``) an "rtlsr" material may have: with the Roy et al. (2016) shape at
#: any wavelength, its black-sky albedo (directional-hemispherical reflectance, ``black_sky_albedo``) then stays
#: <= 1 for every θi in [0, ``DHR_ZENITH_MAX_DEG``]. Established with ``max_black_sky_ratio`` (float64; the
#: table's six band centres and 40 wavelengths over 482-2201 nm; θi in 0..80° by 1°): DHR / ρ rises
#: monotonically with θi and is largest at θi = 80°: 1.29019, so ρ <= 1 / 1.29019 = 0.77508, rounded down.
RHO_MAX = 0.775


def _clamped(cos_i: torch.Tensor, cos_v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return cos_i.clamp(COS_MIN, 1.0), cos_v.clamp(COS_MIN, 1.0)


def ross_thick(cos_i: torch.Tensor, cos_v: torch.Tensor, cos_xi: torch.Tensor) -> torch.Tensor:
    """RossThick volume kernel K_vol = ((π/2 - ξ) cos ξ + sin ξ) / (cos θi + cos θv) - π/4 (Lucht et al. 2000),
    dimensionless; cos θ clamped to ``COS_MIN``, cos ξ to [-1, 1]; inputs broadcast."""
    ci, cv = _clamped(cos_i, cos_v)
    c = cos_xi.clamp(-1.0, 1.0)
    xi = torch.acos(c)
    return ((math.pi / 2 - xi) * c + torch.sin(xi)) / (ci + cv) - math.pi / 4


def li_sparse_r(cos_i: torch.Tensor, cos_v: torch.Tensor, cos_xi: torch.Tensor) -> torch.Tensor:
    """LiSparse-Reciprocal geometric kernel (Lucht et al. 2000; h/b = ``HB``, b/r = 1), dimensionless:

        K_geo = O - sec θi - sec θv + ½ (1 + cos ξ) sec θi sec θv,
        O = (t - sin t cos t)(sec θi + sec θv) / π,
        cos t = (h/b) sqrt(D² + (tan θi tan θv sin φ)²) / (sec θi + sec θv),
        D² = tan²θi + tan²θv - 2 tan θi tan θv cos φ,

    from the cosines: tan θi tan θv cos φ = (cos ξ - cos θi cos θv) / (cos θi cos θv) and
    (tan θi tan θv sin φ)² = tan²θi tan²θv - (tan θi tan θv cos φ)² (>= 0). cos θ clamped to ``COS_MIN``, cos ξ
    and cos t to [-1, 1]; inputs broadcast; symmetric in (θi, θv) to the last bit.
    """
    ci, cv = _clamped(cos_i, cos_v)
    c = cos_xi.clamp(-1.0, 1.0)
    si, sv = 1 / ci, 1 / cv
    ti2, tv2 = (1 - ci) * (1 + ci) * si * si, (1 - cv) * (1 + cv) * sv * sv  # tan²θ
    cc = ci * cv
    p = (c - cc) / cc  # tan θi tan θv cos φ
    d2 = (ti2 + tv2 - 2 * p).clamp_min(0)
    q2 = (ti2 * tv2 - p * p).clamp_min(0)  # (tan θi tan θv sin φ)²
    s = si + sv
    cos_t = (HB * torch.sqrt(d2 + q2) / s).clamp(-1.0, 1.0)
    t = torch.acos(cos_t)
    overlap = (t - torch.sin(t) * cos_t) * s / math.pi
    return overlap - s + 0.5 * (1 + c) * (si * sv)


def reflectance_factor(cos_i: torch.Tensor, cos_v: torch.Tensor, cos_xi: torch.Tensor, f_iso: torch.Tensor,
                       f_vol: torch.Tensor, f_geo: torch.Tensor) -> torch.Tensor:
    """R = f_iso + f_vol K_vol + f_geo K_geo, clamped at 0 (dimensionless); inputs broadcast, band axis last."""
    r = f_iso + f_vol * ross_thick(cos_i, cos_v, cos_xi) + f_geo * li_sparse_r(cos_i, cos_v, cos_xi)
    return r.clamp_min(0)


def rtlsr_brdf_cos(cos_i: torch.Tensor, cos_r: torch.Tensor, cos_2beta: torch.Tensor, f_iso: torch.Tensor,
                   f_vol: torch.Tensor, f_geo: torch.Tensor) -> torch.Tensor:
    """The RTLSR BRDF R / π (sr^-1) from cos θi, cos θr and cos 2β = ω_i·ω_r (the phase angle's cosine, cos ξ),
    0 where cos θi <= 0 or cos θr <= 0; inputs broadcast, band axis last (``reflectance_factor``)."""
    f = reflectance_factor(cos_i, cos_r, cos_2beta, f_iso, f_vol, f_geo) * (1 / math.pi)
    return torch.where((cos_i > 0) & (cos_r > 0), f, torch.zeros_like(f))


# ------------------------------------------------------------------------------------------ kernel weights
def check_kernels(name: object) -> str:
    """The kernel-weight table ``name`` (``KERNEL_TABLES``), or ``ValueError`` naming the parameter."""
    if not isinstance(name, str) or name not in KERNEL_TABLES:
        raise ValueError(f"rtlsr parameter 'kernels' must be one of {', '.join(KERNEL_TABLES)}, got {name!r}")
    return name


def check_rtlsr(reflectance: object, params: dict) -> None:
    """``ValueError`` (one line, naming the parameter) unless ``params`` holds only ``kernels`` (a name of
    ``KERNEL_TABLES``) and every reflectance (white-sky albedo; one value or a list, already checked as numbers in
    [0, 1]) lies in [0, ``RHO_MAX``]."""
    if not isinstance(params, dict):
        raise ValueError(f"rtlsr params must be a dict, got {params!r}")
    unknown = sorted(str(k) for k in params if k != "kernels")
    if unknown:
        raise ValueError(f"unknown rtlsr parameter(s) {', '.join(unknown)}: the only one is 'kernels'")
    check_kernels(params.get("kernels", DEFAULT_KERNELS))
    values = list(reflectance) if isinstance(reflectance, (list, tuple)) else [reflectance]
    for v in values:
        if not (0.0 <= float(v) <= RHO_MAX):  # type: ignore[arg-type]  # numbers, checked by the caller
            raise ValueError(f"rtlsr reflectance (white-sky albedo) must lie in [0, {RHO_MAX}] (above it the "
                             f"black-sky albedo exceeds 1 for θi up to {DHR_ZENITH_MAX_DEG:g}°), got {v}")


def kernel_ratios(wavelength_nm: torch.Tensor, kernels: str = DEFAULT_KERNELS) -> tuple[torch.Tensor, torch.Tensor]:
    """r_vol = f_vol / f_iso and r_geo = f_geo / f_iso at ``wavelength_nm`` (nm), linearly interpolated in
    wavelength between the table's band centres (Roy et al. 2016: 482-2201 nm) and held at the end values
    outside them; same shape, dtype and device as ``wavelength_nm``."""
    rows = sorted(KERNEL_TABLES[check_kernels(kernels)].values())
    nodes = torch.tensor([r[0] for r in rows], dtype=wavelength_nm.dtype, device=wavelength_nm.device)
    r_vol = torch.tensor([r[3] / r[1] for r in rows], dtype=wavelength_nm.dtype, device=wavelength_nm.device)
    r_geo = torch.tensor([r[2] / r[1] for r in rows], dtype=wavelength_nm.dtype, device=wavelength_nm.device)
    x = wavelength_nm.clamp(rows[0][0], rows[-1][0])
    hi = torch.searchsorted(nodes, x.contiguous(), right=True).clamp(1, len(rows) - 1)
    lo = hi - 1
    w = (x - nodes[lo]) / (nodes[hi] - nodes[lo])
    return torch.lerp(r_vol[lo], r_vol[hi], w), torch.lerp(r_geo[lo], r_geo[hi], w)


def kernel_weights(albedo: torch.Tensor, wavelength_nm: torch.Tensor,
                   kernels: str = DEFAULT_KERNELS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(f_iso, f_vol, f_geo) of a material with white-sky albedo ``albedo`` and the table's BRDF shape at
    ``wavelength_nm``: f_iso = ρ / (1 + ``WSA_VOL`` r_vol + ``WSA_GEO`` r_geo), f_vol = r_vol f_iso,
    f_geo = r_geo f_iso (``kernel_ratios``); inputs broadcast."""
    r_vol, r_geo = kernel_ratios(wavelength_nm, kernels)
    f_iso = albedo / (1 + WSA_VOL * r_vol + WSA_GEO * r_geo)
    return f_iso, r_vol * f_iso, r_geo * f_iso


# ---------------------------------------------------------------------------------------------- albedos
def black_sky_albedo(cos_i: torch.Tensor | float, f_iso: torch.Tensor, f_vol: torch.Tensor, f_geo: torch.Tensor,
                     n: int = 200) -> torch.Tensor:
    """The directional-hemispherical reflectance (black-sky albedo) DHR(θi) = (1/π) ∫ R cos θv dω_v of the
    (clamped) RTLSR model at illumination cosines ``cos_i`` (Z,) (or one float), by quadrature in float64 on the
    CPU: Gauss-Legendre in cos θv on [0, cos θi] and [cos θi, 1] (split at the hotspot's kink), ``n`` points each,
    and in φ on [0, π] (R is even in φ), 2 ``n`` points. Weights (B,) or scalars; returns (Z, B) (or (B,))."""
    scalar = not isinstance(cos_i, torch.Tensor) or cos_i.dim() == 0
    ci = torch.as_tensor(cos_i, dtype=torch.float64).reshape(-1, 1)  # (Z, 1)
    x, w = (torch.tensor(a, dtype=torch.float64) for a in np.polynomial.legendre.leggauss(n))
    mu = torch.cat([0.5 * ci * (1 + x), ci + 0.5 * (1 - ci) * (1 + x)], -1)  # (Z, 2n)
    wmu = torch.cat([0.5 * ci * w, 0.5 * (1 - ci) * w], -1)
    xp, wp = (torch.tensor(a, dtype=torch.float64) for a in np.polynomial.legendre.leggauss(2 * n))
    phi, wphi = 0.5 * math.pi * (1 + xp), 0.5 * math.pi * wp  # (2n,)
    si = torch.sqrt((1 - ci) * (1 + ci))
    cos_xi = ci[..., None] * mu[..., None] + (si * torch.sqrt((1 - mu) * (1 + mu)))[..., None] * torch.cos(phi)
    f = [torch.as_tensor(v, dtype=torch.float64) for v in (f_iso, f_vol, f_geo)]
    r = reflectance_factor(ci[..., None, None], mu[..., None, None], cos_xi[..., None], *f)  # (Z, 2n, 2n, B)
    dhr = torch.einsum("zmpb,zm,p->zb", r, wmu * mu, wphi) * (2 / math.pi)
    return dhr[0] if scalar else dhr


def max_black_sky_ratio(wavelengths_nm: Sequence[float], zenith_deg: Sequence[float],
                        kernels: str = DEFAULT_KERNELS, n: int = 200) -> float:
    """The largest DHR(θi) / ρ of the "rtlsr" shape over ``wavelengths_nm`` and illumination zeniths
    ``zenith_deg`` (degrees; ``black_sky_albedo``). R scales with ρ, so ρ <= 1 / this keeps DHR <= 1 there."""
    wl = torch.tensor(list(wavelengths_nm), dtype=torch.float64)
    f_iso, f_vol, f_geo = kernel_weights(torch.ones((), dtype=torch.float64), wl, kernels)
    return max(float(black_sky_albedo(math.cos(math.radians(z)), f_iso[k:k + 8], f_vol[k:k + 8], f_geo[k:k + 8],
                                      n).max()) for z in zenith_deg for k in range(0, len(wl), 8))
