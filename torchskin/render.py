"""Render calibrated multispectral images: G-buffer -> local angles -> BRDF per band -> radiance -> sensor
(eq 2.5.2) -> ELM from the reference panels -> reflectance cube -> NDGRI/NDSI -> rules mask -> detections.

Shapes: S suns, C cameras, H x W pixels, B bands; images are ``(S, C, H, W, B)``. Everything after the
G-buffer runs on the requested device and dtype, without Python loops over pixels.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from . import tissue
from .bands import Band, band_sampling
from .calibrate import elm_coefficients
from .detect import DEFAULT_BOX, RulesBox, has_index_bands, indices, rules_detector
from .optics import THESIS_SPECULAR, skin_brdf_cos, spectralon_brdf_cos, surface_front
from .raycast import GBuffer, Raycaster, rowsum
from .scene import Scene, TriMesh

H_PLANCK = 6.62607015e-34
C_LIGHT = 2.99792458e8


def _per_band(name: str, value, bands: tuple[Band, ...]) -> list[float]:
    """One value per band: a scalar for all, a list of one per band, or four values at 544, 633, 1080 and
    1580 nm (the defaults' bands) interpolated linearly in wavelength for other bands."""
    n = len(bands)
    vals = [float(v) for v in value] if isinstance(value, (list, tuple)) else [float(value)] * n
    if len(vals) == n:
        return vals
    if len(vals) == 4:
        return [float(v) for v in np.interp([b.center_nm for b in bands], [544.0, 633.0, 1080.0, 1580.0], vals)]
    raise ValueError(f"sensor {name} needs one value, one per band ({n}) or four (at 544, 633, 1080, 1580 nm), "
                     f"got {len(vals)}")


@dataclass
class Sensor:
    """Radiometric chain of eq 2.5.2 and the atmosphere of eq 2.5.1, per band (lists or one value).

    L_aperture = τ_atm L + L_path; photoelectrons = L_aperture Ω_pixel A_optic τ_filter Δλ (λ/hc) t_int η;
    then shot noise (Gaussian approximation of Poisson, valid above ~100 e-), read noise, full-well
    clipping and an ADC of ``adc_bits`` with gain full_well / 2^bits e-/DN. Ω_pixel = 1/f_px² comes from
    the camera. Each stage can be switched off: ``atmosphere``, ``noise``, ``quantize``.
    ``integration_time_s="auto"`` exposes each band (each camera of a multi-camera system) so that the
    brightest pixel of the frame fills ``auto_fill`` of the full well (nothing saturates); a number fixes
    it (seconds).
    """

    aperture_diameter_m: float = 0.05
    integration_time_s: float | str = "auto"
    auto_fill: float = 0.8
    quantum_efficiency: float | list = field(default_factory=lambda: [0.55, 0.65, 0.75, 0.70])
    filter_transmittance: float | list = 0.9
    band_width_nm: float | list | None = None  # default: each band's FWHM, or 10 nm for monochromatic bands
    atmosphere_transmittance: float | list = field(default_factory=lambda: [0.95, 0.96, 0.97, 0.93])
    path_radiance: float | list = field(default_factory=lambda: [0.004, 0.003, 0.001, 0.0003])
    read_noise_e: float = 50.0
    full_well_e: float = 2.0e6
    adc_bits: int = 14
    noise: bool = True
    atmosphere: bool = True
    quantize: bool = True
    seed: int = 0

    def __post_init__(self):
        for k in ("aperture_diameter_m", "full_well_e"):
            if not getattr(self, k) > 0:
                raise ValueError(f"sensor {k} must be > 0, got {getattr(self, k)}")
        if self.integration_time_s != "auto" and not float(self.integration_time_s) > 0:
            raise ValueError(f"sensor integration_time_s must be 'auto' or > 0 s, got {self.integration_time_s}")
        if not (0 < self.auto_fill <= 1):
            raise ValueError(f"sensor auto_fill must lie in (0, 1], got {self.auto_fill}")
        if not (1 <= int(self.adc_bits) <= 32):
            raise ValueError(f"sensor adc_bits must lie in [1, 32], got {self.adc_bits}")

    def tables(self, bands: tuple[Band, ...], dtype, device) -> dict[str, torch.Tensor]:
        widths = self.band_width_nm
        if widths is None:
            widths = [b.fwhm_nm if b.fwhm_nm > 0 else 10.0 for b in bands]
        t = {
            "qe": _per_band("quantum_efficiency", self.quantum_efficiency, bands),
            "filter": _per_band("filter_transmittance", self.filter_transmittance, bands),
            "width": _per_band("band_width_nm", widths, bands),
            "tau": _per_band("atmosphere_transmittance", self.atmosphere_transmittance, bands),
            "path": _per_band("path_radiance", self.path_radiance, bands),
            "wavelength_m": [b.center_nm * 1e-9 for b in bands],
        }
        for k in ("qe", "filter", "tau"):
            if not all(0 < v <= 1 for v in t[k]):
                raise ValueError(f"sensor {k} values must lie in (0, 1], got {t[k]}")
        return {k: torch.tensor(v, dtype=dtype, device=device) for k, v in t.items()}


def band_max(x: torch.Tensor) -> torch.Tensor:
    """Max over axis 2 of (S, C, N, B) -> (S, C, B). Reducing a strided middle axis with 4 bands innermost is
    ~60x slower on CPU than two reductions over 64-wide contiguous rows, so the frame is viewed that way."""
    S, C, N, B = x.shape
    k = B * max(1, 64 // B)
    if not x.is_contiguous() or (N * B) % k:
        return x.amax(dim=2)
    return x.reshape(S * C, -1, k).amax(dim=1).reshape(S * C, k // B, B).amax(dim=1).reshape(S, C, B)


def sensor_signal(radiance: torch.Tensor, sensor: Sensor | None, bands, focal_px: float,
                  generator: torch.Generator | None = None, reference: torch.Tensor | None = None) -> torch.Tensor:
    """Digital numbers from at-surface radiance (W m^-2 sr^-1 nm^-1) of shape ``(S, C, ..., B)``.
    ``sensor=None`` returns the radiance unchanged (an ideal linear sensor). ``reference`` (S, C, B): the
    radiance that automatic exposure maps to ``auto_fill`` of the full well (default: the frame's maximum).

    Shot and read noise are independent Gaussians, drawn as one: σ² = N_e + σ_read² (electrons).
    """
    if sensor is None:
        return radiance
    tb = sensor.tables(tuple(bands), radiance.dtype, radiance.device)
    S, C, B = radiance.shape[0], radiance.shape[1], radiance.shape[-1]
    mid = (1,) * (radiance.dim() - 3)
    L = torch.addcmul(tb["path"], tb["tau"], radiance) if sensor.atmosphere else radiance
    omega = 1.0 / focal_px**2
    area = math.pi * (sensor.aperture_diameter_m / 2) ** 2
    k = omega * area * tb["filter"] * tb["width"] * tb["wavelength_m"] * tb["qe"] / (H_PLANCK * C_LIGHT)
    if sensor.integration_time_s == "auto":
        if reference is None:
            reference = band_max(radiance.reshape(S, C, -1, B))
        ref = torch.addcmul(tb["path"], tb["tau"], reference) if sensor.atmosphere else reference
        t_int = sensor.auto_fill * sensor.full_well_e / (k * ref).clamp_min(1e-30)  # (S, C, B)
        k = (k * t_int).reshape(S, C, *mid, B)
    else:
        k = k * float(sensor.integration_time_s)
    levels = 2 ** int(sensor.adc_bits)
    g = levels / sensor.full_well_e  # DN per electron
    dn = L * (k * g)
    if sensor.noise:
        z = torch.randn(dn.shape, generator=generator, dtype=dn.dtype, device=dn.device)
        dn = dn.addcmul(dn.clamp_min(0).mul_(g).add_((sensor.read_noise_e * g) ** 2).sqrt_(), z)
    if sensor.quantize:
        return torch.round(dn).clamp_(0, levels - 1)
    return dn.clamp(0, levels * 1.0)


# -------------------------------------------------------------------------------------- material tables
@dataclass
class MaterialTables:
    """Per-material, per-band quantities gathered by material id: (M, B) each."""

    lambert_f: torch.Tensor  # ρ/π for lambertian materials, 0 for skin
    albedo: torch.Tensor  # hemispherical reflectance for the sky term (skin: the diffuse model's)
    is_skin: torch.Tensor  # (M,) bool: combined skin BRDF
    r_sub: torch.Tensor  # skin subsurface reflectance R_sub per band (band-averaged under the sun)
    sigma2: torch.Tensor  # (B,)
    rho0: torch.Tensor  # (B,)
    irradiance: torch.Tensor  # (S, B) sun normal irradiance per band, W m^-2 nm^-1
    panel_brdf: torch.Tensor  # (M,) bool: Spectralon-like BRDF (optics.spectralon_brdf_cos)
    dhr: torch.Tensor  # (M, B) hemispherical reflectance of lambertian / spectralon materials
    wavelengths: torch.Tensor  # (B,) band centres, nm
    skin_ids: tuple = ()  # host copies of the flags above: which materials need each BRDF (no device sync)
    panel_brdf_ids: tuple = ()
    skin_front: torch.Tensor | None = None  # (M, 1): weight of R0 in the skin's ρ_d, 1 "thesis", 0 "conserving"


_TABLE_CACHE: dict = {}


def material_tables(scene: Scene, names: list[str], dtype, device) -> MaterialTables:
    """Per-material band tables (cached: the skin model runs once per distinct material set and sun)."""
    import json

    key = (json.dumps([[dataclasses.asdict(scene.materials[n]) for n in names], scene.bands,
                       [(s.temperature_k, s.scale) for s in scene.suns]], sort_keys=True), str(dtype), str(device))
    hit = _TABLE_CACHE.get(key)
    if hit is None:
        if len(_TABLE_CACHE) > 64:
            _TABLE_CACHE.clear()
        hit = _TABLE_CACHE[key] = _material_tables(scene, names, dtype, device)
    return hit


def _material_tables(scene: Scene, names: list[str], dtype, device) -> MaterialTables:
    bands = scene.band_list
    grid, W = band_sampling(bands, dtype=torch.float64)
    E = torch.stack([s.irradiance(grid) for s in scene.suns])  # (S, G)
    e_band = E @ W  # (S, B)
    wE = W * E[0][:, None]  # weights under the first sun's spectrum
    wE = wE / wE.sum(0)
    M, B = len(names), len(bands)
    lam = torch.zeros(M, B, dtype=torch.float64)
    alb = torch.zeros(M, B, dtype=torch.float64)
    rsub = torch.zeros(M, B, dtype=torch.float64)
    skin = torch.zeros(M, dtype=torch.bool)
    pbrdf = torch.zeros(M, dtype=torch.bool)
    dhr = torch.zeros(M, B, dtype=torch.float64)
    front = torch.zeros(M, 1, dtype=torch.float64)
    for k, name in enumerate(names):
        m = scene.materials[name]
        if m.kind == "skin":
            front[k] = surface_front(m.surface)
            p = m.skin_params(dtype=torch.float64)
            r_sub_grid = tissue.subsurface_reflectance(p, grid)  # once per material: both quantities derive from it
            rs = r_sub_grid @ wE
            rtot = tissue.surface_total(torch.tensor(0.04, dtype=torch.float64), r_sub_grid) @ wE
            alb[k] = rtot
            if m.specular:
                skin[k] = True
                rsub[k] = rs
            else:  # the diffuse-only model: a Lambertian surface with the normal-incidence skin reflectance
                lam[k] = rtot / math.pi
        else:
            r = torch.tensor(m.band_reflectance(bands), dtype=torch.float64)
            lam[k] = r / math.pi
            alb[k] = r
            dhr[k] = r
            pbrdf[k] = m.brdf
    wl = torch.tensor([b.center_nm for b in bands], dtype=torch.float64)
    sig, rho0 = THESIS_SPECULAR.at(wl)

    def dev(x):
        return x.to(device=device, dtype=dtype) if x.is_floating_point() else x.to(device)

    return MaterialTables(dev(lam), dev(alb), dev(skin), dev(rsub), dev(sig), dev(rho0), dev(e_band), dev(pbrdf),
                          dev(dhr), dev(wl), tuple(skin.nonzero().flatten().tolist()),
                          tuple(pbrdf.nonzero().flatten().tolist()), dev(front))


def local_cosines(gb: GBuffer, idx: torch.Tensor, sun_dirs: torch.Tensor):
    """cos θi (S, K, 1, clamped at 0), cos θr (1, K, 1) and cos 2β = ω_i·ω_r (S, K, 1) at flat pixels ``idx``."""
    ns = gb.normal.reshape(-1, 3).index_select(0, idx)
    vs = gb.view.reshape(-1, 3).index_select(0, idx)
    ci = (sun_dirs @ ns.T).clamp_min(0)[..., None]
    cr = rowsum(ns * vs)[None, :, None]
    c2b = (sun_dirs @ vs.T)[..., None]
    return ci, cr, c2b


def _skin_brdf(ci, cr, c2b, mat, tables):
    """Eq 3.1.1 with ρ_d from the exact closed form in R0 = Schlick(ρ0, θi), per the material's skin surface
    model (``optics.skin_brdf_cos``)."""
    r_sub = tables.r_sub.index_select(-2, mat)  # (K, B), or (S, K, B) for per-sun skins
    return skin_brdf_cos(ci, cr, c2b, r_sub, tables.sigma2, tables.rho0, tables.skin_front.index_select(0, mat))


def _panel_brdf(ci, cr, c2b, mat, tables):
    return spectralon_brdf_cos(ci, cr, c2b, tables.dhr.index_select(0, mat), tables.wavelengths)


def shade(gb: GBuffer, tables: MaterialTables, sun_dirs: torch.Tensor, sky_fraction: torch.Tensor,
          dense: bool | None = None, sky_background: bool = False) -> dict:
    """At-surface radiance (S, C, H, W, B), W m^-2 sr^-1 nm^-1, and the sunlit mask (S, C, H, W).

    Sunlit: L = f(θi, θr, Δφ) E cos θi, with f the combined skin BRDF (eq 3.1.1, ρ_d from the exact closed
    form in R0 = Schlick(ρ0, θi)) on skin pixels and ρ/π elsewhere; plus a uniform sky on every hit pixel,
    ρ_hemi/π · E_sky · (1 + n_z)/2. On the CPU the skin (and panel) BRDF is evaluated on its pixels only
    (gathered); with ``dense`` (the default on accelerators) on every pixel and selected, so that shading
    waits for no data-dependent pixel count (no host round trip). ``sky_background``: rays that hit nothing
    and point above the horizon see the uniform sky itself, radiance sky_fraction · E / π (the dome whose
    irradiance on a horizontal surface is sky_fraction · E); otherwise missed rays carry no radiance.
    """
    shp = gb.hit.shape  # (C, H, W)
    S = sun_dirs.shape[0]
    n = gb.normal.reshape(-1, 3)
    hit = gb.hit.reshape(-1)
    mat = gb.material.reshape(-1).clamp_min(0)
    cos_i = sun_dirs @ n.T  # (S, N)
    lit = (cos_i > 0) & ~gb.shadow.reshape(S, -1) & hit
    w = torch.where(lit, cos_i, torch.zeros((), dtype=cos_i.dtype, device=cos_i.device))  # (S, N)
    E = tables.irradiance[:, None, :]  # (S, 1, B)
    sky = (tables.albedo.index_select(-2, mat) * (hit * (0.5 / math.pi) * (1 + n[:, 2]))[:, None])  # ([S,] N, B)
    L = torch.addcmul((sky_fraction[:, None, None] * E) * sky, w[..., None], tables.lambert_f.index_select(-2, mat) * E)
    if dense is None:
        dense = n.device.type != "cpu"
    if dense and (tables.skin_ids or tables.panel_brdf_ids):  # every pixel's geometry and Lambertian part, once
        v = gb.view.reshape(-1, 3)
        ci, cr, c2b = cos_i.clamp_min(0)[..., None], rowsum(n * v)[None, :, None], (sun_dirs @ v.T)[..., None]
        wE = w[..., None] * E
        lam_part = wE * tables.lambert_f.index_select(-2, mat)
    for flag, brdf, ids in ((tables.is_skin, _skin_brdf, tables.skin_ids),
                            (tables.panel_brdf, _panel_brdf, tables.panel_brdf_ids)):
        if not ids:
            continue
        if dense:
            f = brdf(ci, cr, c2b, mat, tables)  # (S, N, B)
            L = torch.where((hit & flag[mat])[:, None], torch.addcmul(L - lam_part, wE, f), L)
            continue
        idx = (hit & flag[mat]).nonzero().flatten()
        if idx.numel():
            ci, cr, c2b = local_cosines(gb, idx, sun_dirs)
            f = brdf(ci, cr, c2b, mat.index_select(0, idx), tables)  # (S, K, B)
            lam_part = w.index_select(1, idx)[..., None] * E * tables.lambert_f.index_select(-2, mat.index_select(0, idx))
            Ls = torch.addcmul(L.index_select(1, idx) - lam_part, w.index_select(1, idx)[..., None] * E, f)
            L = L.index_copy(1, idx, Ls)
    if sky_background:
        up = ~hit & (gb.view.reshape(-1, 3)[:, 2] < 0)  # the ray (-view) climbs
        L = torch.where(up[:, None], sky_fraction[:, None, None] * E * (1 / math.pi), L)
    B = L.shape[-1]
    return {"radiance": L.reshape(S, *shp, B), "lit": lit.reshape(S, *shp)}


# ----------------------------------------------------------------------------------------------------- ELM
def erode(mask: torch.Tensor, pixels: int = 1) -> torch.Tensor:
    """Binary erosion of (..., H, W) masks with a (2p+1)² square (on the mask's device)."""
    if pixels <= 0:
        return mask
    shp = mask.shape
    m = (~mask).reshape(-1, 1, *shp[-2:]).to(torch.float32)
    grown = F.max_pool2d(m, 2 * pixels + 1, stride=1, padding=pixels)
    return (grown < 0.5).reshape(shp) & mask


def panel_pixels(gb: GBuffer, panel_names: list[str], erode_px: int = 1) -> list[list[torch.Tensor]]:
    """Flat indices (into H*W) of each panel's interior pixels per camera: ``[panel][camera]``. Raises if
    a camera sees no interior pixel of a panel (ELM impossible). Cached on the G-buffer."""
    key = ("panel_pixels", tuple(panel_names), erode_px)
    if key in gb.cache:
        return gb.cache[key]
    out = []
    W = gb.mesh.shape[-1]
    for name in panel_names:
        k = gb.mesh_names.index(name)
        per_cam = []
        for c in range(gb.mesh.shape[0]):
            m = gb.mesh[c] == k
            rows, cols = m.any(1).nonzero().flatten(), m.any(0).nonzero().flatten()
            if rows.numel() == 0:
                per_cam.append(rows)
                continue
            y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
            inner = erode(m[y0:y1, x0:x1], erode_px).nonzero()  # erode only the panel's bounding box
            per_cam.append((inner[:, 0] + y0) * W + inner[:, 1] + x0)
        empty = [c for c, ix in enumerate(per_cam) if ix.numel() == 0]
        if empty:
            raise ValueError(f"camera(s) {empty} see no interior pixel of reference panel {name!r}: ELM impossible")
        out.append(per_cam)
    gb.cache[key] = out
    return out


def panel_regions(gb: GBuffer, panel_names: list[str], erode_px: int = 1, camera: int = 0) -> dict[str, list[int]]:
    """An axis-aligned rectangle [y0, y1, x0, x1] (rows y0..y1-1, columns x0..x1-1) of each panel's interior
    pixels in one camera's image: the bounding box of the interior, shrunk from its emptiest side until every
    pixel inside is interior (for ELM from pixel regions, e.g. ``torchskin calibrate``)."""
    H, W = gb.hit.shape[-2:]
    out = {}
    for name, per_cam in zip(panel_names, panel_pixels(gb, panel_names, erode_px)):
        m = np.zeros(H * W, dtype=bool)
        m[per_cam[camera].cpu().numpy()] = True
        m = m.reshape(H, W)
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        while y1 > y0 and x1 > x0 and not m[y0:y1, x0:x1].all():
            sub = m[y0:y1, x0:x1]
            empty = [(~sub[0]).mean(), (~sub[-1]).mean(), (~sub[:, 0]).mean(), (~sub[:, -1]).mean()]
            k = int(np.argmax(empty))
            y0, y1, x0, x1 = y0 + (k == 0), y1 - (k == 1), x0 + (k == 2), x1 - (k == 3)
        out[name] = [y0, y1, x0, x1]
    return out


def panel_values(x: torch.Tensor, pixels: list[list[torch.Tensor]]) -> torch.Tensor:
    """Median of ``x`` (S, C, H, W, B) over each panel's interior pixels: (S, C, P, B)."""
    flat = x.flatten(2, 3)  # (S, C, H*W, B)
    return torch.stack([torch.stack([flat[:, c].index_select(1, ix).median(dim=1).values
                                     for c, ix in enumerate(per_cam)], dim=1) for per_cam in pixels], dim=2)


def detections(mask: np.ndarray, truth: np.ndarray | None = None, min_area: int = 4) -> list[dict]:
    """Connected components of a 2-D mask (scikit-image): bounding box, area, centroid, and the fraction
    of the component on the truth mask when given."""
    from skimage.measure import label, regionprops

    lab = label(mask, connectivity=2)
    out = []
    for r in regionprops(lab):
        if r.area < min_area:
            continue
        d = {"bbox": [int(x) for x in r.bbox], "area": int(r.area),
             "centroid": [float(r.centroid[0]), float(r.centroid[1])]}
        if truth is not None:
            d["on_subject"] = float(truth[lab == r.label].mean())
        out.append(d)
    return sorted(out, key=lambda d: -d["area"])


# ---------------------------------------------------------------------------------------------- rendering
@dataclass
class RenderResult:
    radiance: torch.Tensor  # (S, C, H, W, B)
    signal: torch.Tensor  # DN (or radiance without a sensor)
    reflectance: torch.Tensor  # ELM-calibrated
    ndgri: torch.Tensor  # (S, C, H, W)
    ndsi: torch.Tensor
    mask: torch.Tensor  # rules detector
    skin: torch.Tensor  # (C, H, W) ground truth: skin pixels
    lit: torch.Tensor  # (S, C, H, W) sunlit
    panels: dict
    gbuffer: GBuffer
    timing: dict
    bands: tuple


def build_meshes(scene: Scene) -> tuple[list[TriMesh], list[str]]:
    meshes = [m.build() for m in scene.meshes]
    names = list(scene.materials)
    return meshes, names


def panel_references(scene: Scene, gb: GBuffer, tables: MaterialTables, sun_dirs: torch.Tensor,
                     pix: list[list[torch.Tensor]], elm: str = "dhr") -> torch.Tensor:
    """Reference reflectance of each panel (S, C, P, B). ``elm="dhr"``: the panels' hemispherical
    reflectance (the usual ELM, eqs 2.5.5-2.5.6); ``elm="brdf"``: π f_BRDF of each panel at its pixels'
    source/view geometry (median over the interior), i.e. BRDF-ELM (eqs 3.3.1-3.3.3) in Lambertian-
    equivalent units (identical to "dhr" for Lambertian panels)."""
    if elm not in ("dhr", "brdf"):
        raise ValueError(f"elm must be 'dhr' or 'brdf', got {elm!r}")
    S, C = sun_dirs.shape[0], gb.hit.shape[0]
    HW = gb.hit[0].numel()
    out = []
    for k, name in enumerate(scene.panels):
        m = gb.material_names.index(scene.mesh(name).material)
        ref = tables.dhr[m].expand(S, C, -1)
        if elm == "brdf" and m in tables.panel_brdf_ids:
            per_cam = []
            for c, ix in enumerate(pix[k]):
                ci, cr, c2b = local_cosines(gb, ix + c * HW, sun_dirs)
                f = _panel_brdf(ci, cr, c2b, torch.full_like(ix, m), tables)  # (S, K, B)
                per_cam.append(math.pi * f.median(dim=1).values)
            ref = torch.stack(per_cam, dim=1)
        out.append(ref)
    return torch.stack(out, dim=2)


def apply_elm(signal: torch.Tensor, panel_signal: torch.Tensor, references: torch.Tensor) -> torch.Tensor:
    """Map signals (S, C, H, W, B) to reflectance with the line through the first two panels (eq 2.5.7)."""
    a, b = elm_coefficients(panel_signal[:, :, 0], panel_signal[:, :, 1], references[:, :, 0], references[:, :, 1])
    inv_a = 1 / a[:, :, None, None, :]
    return torch.addcmul(-b[:, :, None, None, :] * inv_a, signal, inv_a)  # (L - b) / a


def skin_batched_tables(scene: Scene, names: list[str], skins: list, dtype, device) -> MaterialTables:
    """Tables for ``len(skins)`` x S 'suns': skin k (a preset name or parameter dict for the material named
    "skin") with every sun, skin-major. The skin-dependent fields get a leading (K*S) axis."""
    import copy

    S = len(scene.suns)
    per = []
    for sk in skins:
        sc = copy.copy(scene)
        sc.materials = {**scene.materials, "skin": dataclasses.replace(scene.materials["skin"], skin=sk)}
        per.append(material_tables(sc, names, dtype, device))
    t0 = per[0]

    def stack(field):
        return torch.stack([getattr(t, field) for t in per]).repeat_interleave(S, 0)  # (K*S, M, B)

    return dataclasses.replace(t0, lambert_f=stack("lambert_f"), albedo=stack("albedo"), r_sub=stack("r_sub"),
                               irradiance=t0.irradiance.repeat(len(skins), 1))


def gather_pixels(gb: GBuffer, flat: torch.Tensor) -> GBuffer:
    """A G-buffer of the pixels ``flat`` (indices into the single camera's H*W), shaped (1, 1, K)."""
    if gb.hit.shape[0] != 1:
        raise ValueError("pixel subsets need a single camera")
    out = {}
    for f in dataclasses.fields(gb):
        v = getattr(gb, f.name)
        if f.name == "shadow":
            out[f.name] = v.flatten(1).index_select(1, flat).reshape(v.shape[0], 1, 1, -1)
        elif isinstance(v, torch.Tensor):
            tail = v.shape[3:]
            out[f.name] = v.reshape(-1, *tail).index_select(0, flat).reshape(1, 1, -1, *tail)
        elif f.name != "cache":
            out[f.name] = v
    return GBuffer(**out)


def render(scene: Scene, device="cpu", dtype=torch.float32, sensor: Sensor | None = None,
           box: RulesBox = DEFAULT_BOX, raycaster: Raycaster | None = None, gbuffer: GBuffer | None = None,
           erode_px: int = 1, elm: str = "dhr", pixels: torch.Tensor | None = None,
           skins: list | None = None) -> RenderResult:
    """Render every sun x camera of ``scene`` and calibrate with ELM. ``sensor=None`` uses an ideal linear
    sensor (ELM then recovers Lambertian reflectance exactly). ``elm="brdf"`` calibrates with the panels'
    BRDF at the scene geometry (BRDF-ELM) instead of their DHR. Pass ``raycaster``/``gbuffer`` to reuse
    geometry across calls.

    ``pixels`` (flat indices into the single camera's H*W) renders only those pixels and the panels'
    interior: images then have shape (S, 1, 1, K, ...) for the K requested pixels, and automatic exposure
    uses the brightest of them (the dataset generator's fast path).

    ``skins`` (presets or parameter dicts for the material named "skin") renders every skin under every sun
    in one batch: the leading axis of the outputs is then skin-major (len(skins) x S)."""
    device = torch.device(device)
    timing = {}
    t0 = time.perf_counter()
    if gbuffer is None:
        if raycaster is None:
            meshes, names = build_meshes(scene)
            timing["build_s"] = time.perf_counter() - t0
            raycaster = Raycaster(meshes, names)
        t1 = time.perf_counter()
        sun_dirs_np = np.stack([s.direction for s in scene.suns])
        gbuffer = raycaster.gbuffer(scene.cameras, sun_dirs_np)
        timing["raycast_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    gb = gbuffer.to(device=device, dtype=dtype)
    pix = panel_pixels(gb, list(scene.panels), erode_px)
    if pixels is not None:
        pixels = pixels.to(gb.hit.device).long()
        panel_flat = [per_cam[0] for per_cam in pix]
        sizes = [len(pixels)] + [len(x) for x in panel_flat]
        gb = gather_pixels(gb, torch.cat([pixels, *panel_flat]))
        offs = np.cumsum(sizes)
        pix = [[torch.arange(int(offs[k]), int(offs[k + 1]), device=gb.hit.device)] for k in range(len(panel_flat))]
    reps = 1
    if skins is not None:
        if "skin" not in scene.materials or not skins:
            raise ValueError("skins needs a material named 'skin' and at least one skin")
        reps = len(skins)
        tables = skin_batched_tables(scene, gb.material_names, skins, dtype, device)
        gb = dataclasses.replace(gb, shadow=gb.shadow.repeat(reps, *([1] * (gb.shadow.dim() - 1))), cache={})
    else:
        tables = material_tables(scene, gb.material_names, dtype, device)
    bands = scene.band_list
    sun_dirs = torch.tensor(np.stack([s.direction for s in scene.suns]), dtype=dtype, device=device).repeat(reps, 1)
    sky = torch.tensor([s.sky_fraction for s in scene.suns], dtype=dtype, device=device).repeat(reps)
    sh = shade(gb, tables, sun_dirs, sky, sky_background=scene.background == "sky")
    _sync(device)
    timing["shade_s"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    gen = None
    if sensor is not None and sensor.noise:
        gen = torch.Generator(device=device)
        gen.manual_seed(int(sensor.seed))
    focal = scene.cameras[0].focal
    signal = sensor_signal(sh["radiance"], sensor, bands, focal, gen)
    pv = panel_values(signal, pix)  # (S, C, P, B)
    refs = panel_references(scene, gb, tables, sun_dirs, pix, elm)  # (S, C, P, B)
    refl = apply_elm(signal, pv, refs)
    if has_index_bands(bands):
        g, s = indices(refl, bands)
        mask = rules_detector(g, s, box) & gb.hit
    else:  # the rules need 544, 633, 1080 and 1580 nm: reflectance only
        g = s = torch.full(refl.shape[:-1], math.nan, dtype=refl.dtype, device=refl.device)
        mask = torch.zeros_like(gb.hit).expand(refl.shape[:-1])
    skin_mat = torch.tensor([scene.materials[n].kind == "skin" for n in gb.material_names], device=device)
    skin = gb.hit & skin_mat[gb.material.clamp_min(0)]
    _sync(device)
    timing["sensor_elm_s"] = time.perf_counter() - t3
    timing["total_s"] = time.perf_counter() - t0
    panels = {p: {"reference": refs[:, :, k].tolist(), "signal": pv[:, :, k].tolist()}
              for k, p in enumerate(scene.panels)}
    if pixels is not None:  # keep the requested pixels only
        n = len(pixels)
        return RenderResult(sh["radiance"][..., :n, :], signal[..., :n, :], refl[..., :n, :], g[..., :n],
                            s[..., :n], mask[..., :n], skin[..., :n], sh["lit"][..., :n], panels, gb, timing, bands)
    return RenderResult(sh["radiance"], signal, refl, g, s, mask, skin, sh["lit"], panels, gb, timing, bands)


def _sync(device: torch.device) -> None:
    """Wait for queued device work (for stage timings)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


#: a frame's ELM is physical when at least this share of every reference panel's interior is sunlit (the rule
#: of the dataset generator's ``elm_valid``)
ELM_MIN_SUNLIT = 0.5


def panel_sunlit_fraction(result: RenderResult, s: int = 0, c: int = 0) -> list[float]:
    """Per reference panel (``result.panels`` order), the sunlit share of its interior pixels for sun ``s``
    and camera ``c`` (a full-frame render)."""
    lit = result.lit[s, c].reshape(-1)
    pix = panel_pixels(result.gbuffer, list(result.panels))
    return [float(lit.index_select(0, per_cam[c]).float().mean()) for per_cam in pix]


def summary(result: RenderResult, s: int = 0, c: int = 0) -> dict:
    """Skin pixel counts and the fraction the rules detector finds, for sun ``s`` and camera ``c``; whether the
    frame's ELM is physical (``elm_valid``: every reference panel at least ``ELM_MIN_SUNLIT`` sunlit; without
    sunlit panels the empirical line is set by sky light and reflectance can exceed 1)."""
    skin = result.skin[c]
    lit = skin & result.lit[s, c]
    det = result.mask[s, c]
    n, nl = int(skin.sum()), int(lit.sum())
    sunlit = panel_sunlit_fraction(result, s, c)
    return {
        "skin_pixels": n,
        "sunlit_skin_pixels": nl,
        "detected_fraction": float(det[skin].float().mean()) if n else 0.0,
        "detected_fraction_sunlit": float(det[lit].float().mean()) if nl else 0.0,
        "false_alarm_pixels": int((det & ~skin).sum()),
        "rules_detector": has_index_bands(result.bands),  # false: the bands lack 544/633/1080/1580 nm
        "elm_valid": all(f >= ELM_MIN_SUNLIT for f in sunlit),
        "panel_sunlit_fraction": sunlit,
    }


def write_outputs(result: RenderResult, scene: Scene, out_dir, s: int = 0, c: int = 0) -> dict:
    """Band PNGs (false-colour reflectance), the reflectance cube (bands x H x W, ``reflectance.npy``), the
    sensor signal cube before ELM (``signal.npy``, digital numbers), the rules detector's mask, ``mask.png``: an
    RGB PNG of exactly the frame's H x W pixels (one per frame pixel, no axes or title; ``plots.mask_png``),
    detected skin green (26, 217, 51), missed skin red (230, 38, 26), false alarms yellow (255, 230, 26),
    everything else black; the same mask as an annotated figure with a colour key, ``mask_annotated.png``; and
    ``render.json`` (scene, timing, panels with their pixel regions, detections). Returns the summary."""
    from pathlib import Path

    from .io import save_npy, write_text
    from .plots import band_image, mask_image, mask_png

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cube = result.reflectance[s, c].permute(2, 0, 1).contiguous().cpu().float().numpy()
    signal = result.signal[s, c].permute(2, 0, 1).contiguous().cpu().float().numpy()
    save_npy(out / "reflectance.npy", cube)
    save_npy(out / "signal.npy", signal)
    for k, b in enumerate(result.bands):
        band_image(out / f"band_{b.center_nm:g}nm.png", result.reflectance[s, c, :, :, k],
                   f"{b.center_nm:g} nm reflectance (ELM)")
    mask_png(out / "mask.png", result.mask[s, c], result.skin[c])
    mask_image(out / "mask_annotated.png", result.mask[s, c], result.skin[c],
               f"rules detector mask ({result.mask.shape[-1]} x {result.mask.shape[-2]} px)")
    info = summary(result, s, c)
    dets = detections(result.mask[s, c].cpu().numpy(), result.skin[c].cpu().numpy())
    import json

    regions = panel_regions(result.gbuffer, list(scene.panels), camera=c)
    panels = {p: {**v, "region": regions[p]} for p, v in result.panels.items()}
    doc = {"summary": info, "timing_s": result.timing, "panels": panels, "detections": dets,
           "scene": scene.to_dict(), "bands_nm": [[b.center_nm, b.fwhm_nm] for b in result.bands]}
    write_text(out / "render.json", json.dumps(doc, indent=1))
    return info
