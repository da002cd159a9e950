"""Stage 6 of the renderer: the empirical line method (eqs 2.5.4-2.5.7), digital numbers + reference-panel
pixels -> reflectance; and its BRDF form (eqs 3.3.1-3.3.3) through the panels' BRDF at the scene geometry.

The onboard runtime (numpy only) has its own copy, ``onboard.elm_apply``, tested equal to ``apply_elm``.

>>> import torch
>>> L1, L2, ref1, ref2 = (torch.tensor([x], dtype=torch.float64) for x in (970.0, 30.0, 0.97, 0.03))
>>> a, b = elm_coefficients(L1, L2, ref1, ref2)
>>> round(float(a), 9), round(float(b), 9) + 0.0  # L = a ρ + b
(1000.0, 0.0)
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .._checks import TensorLike, as_tensor
from .kernels import elm_line
from .materials import MaterialTables
from .raycast import GBuffer
from .shade import gather_params, pixel_cosines

#: a frame's ELM is physical when at least this share of every reference panel's interior is sunlit (the rule
#: of the dataset generator's ``elm_valid``)
ELM_MIN_SUNLIT = 0.5
#: the empirical line is a line when, in every band, its two panels' signals differ by at least this many standard
#: deviations of that difference (the noise of the two sampled medians, ``panel_median_noise_dn``). The gain's
#: relative error is then at most 1/20 = 5 % (1σ): a reflectance of 1 reads 1 ± 0.05; and a pair of panels with no
#: real contrast (the same light on both, or both clipped) reaches 20σ by noise with odds below 1e-80
ELM_MIN_SEPARATION_SIGMA = 20.0
#: the empirical line stands for the scene's light when no surface the sun and sky can reach receives more than this
#: many times the reference panels' irradiance (``panel_irradiance_ratio``). Through the line, a sunlit Lambertian
#: surface of reflectance ρ reads up to ρ times that ratio: at most 3, a white surface (0.97) reads at most 2.9 and
#: skin's diffuse reflectance (at most ~0.65 in the detector's bands) at most ~2, an error the configuration-dependent
#: boundaries can learn, since the ratio is set by the sun and the panels. Beyond it, a low sun grazes level panels
#: (the ratio is ~1/cos θz under a clear sky) while it lights the subject's sun-facing side head on, or the panels are
#: turned from the sun while the subject faces it, and the line maps such surfaces to many times their reflectance
#: (up to ~150 at an 89° sun). Measured on ``generate --configs 2400 --seed 1`` (2,271 configurations valid by the
#: other rules, 4,279 of their rows above 3): a bound of 2 drops 33 % of them and leaves 33 of 759 with the sun
#: >= 60° (no row above 3); 3 drops 22 % and keeps 267 of 759 (20 rows above 3, at most 5.1: skin's specular glint at
#: forward grazing geometry, a true reading); 5 drops 12 % (151 rows above 3, up to 11.9)
ELM_MAX_IRRADIANCE_RATIO = 3.0


def elm_coefficients(L1: TensorLike, L2: TensorLike, ref1: TensorLike,
                     ref2: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Gain and offset ``(a, b)`` of L = a·ρ + b from two panels (eqs 2.5.5-2.5.6).

    ``L1``, ``L2``: measured signals of panels 1 and 2; ``ref1``, ``ref2``: their known reflectances (or,
    for BRDF-ELM, their BRDF values at the scene geometry).
    """
    L1 = as_tensor(L1)
    L2, ref1, ref2 = (as_tensor(x, like=L1) for x in (L2, ref1, ref2))
    if bool((ref2 - ref1 == 0).any()):
        raise ValueError("ref1 and ref2 must differ in every band (the empirical line is undefined otherwise)")
    return _line(L1, L2, ref1, ref2)


def _line(L1: torch.Tensor, L2: torch.Tensor, ref1: torch.Tensor, ref2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gain and offset of the line through (ref1, L1) and (ref2, L2), unchecked (eqs 2.5.5-2.5.6)."""
    dref = ref2 - ref1
    return (L2 - L1) / dref, (L1 * ref2 - L2 * ref1) / dref


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
    a camera sees no interior pixel of a panel (ELM impossible)."""
    out = []
    W = gb.mesh.shape[-1]
    for name in panel_names:
        k = gb.mesh_names.index(name)
        per_cam = []
        for c in range(gb.mesh.shape[0]):
            m = gb.mesh[c] == k
            flat = m.reshape(-1).nonzero().flatten()  # row-major: the first and last are in the extreme rows
            if flat.numel() == 0:
                per_cam.append(flat)
                continue
            x = flat % W
            y0, y1, x0, x1 = int(flat[0]) // W, int(flat[-1]) // W + 1, int(x.min()), int(x.max()) + 1
            inner = erode(m[y0:y1, x0:x1], erode_px).nonzero()  # erode only the panel's bounding box
            per_cam.append((inner[:, 0] + y0) * W + inner[:, 1] + x0)
        empty = [c for c, ix in enumerate(per_cam) if ix.numel() == 0]
        if empty:
            raise ValueError(f"camera(s) {empty} see no interior pixel of reference panel {name!r}: ELM impossible")
        out.append(per_cam)
    return out


def panel_subset(pixels: list[list[torch.Tensor]], cap: int) -> list[list[torch.Tensor]]:
    """At most ``cap`` of each panel's interior pixels per camera (``panel_pixels``): a regular subset of the
    sorted flat indices (every k-th, k = ceil(n / cap)), spread over the whole panel, so that its median stands for
    the interior's (the dataset generator's capped panel sample: the panels' interiors otherwise outnumber the
    sampled pixels of a frame many times over)."""
    if cap < 1:
        raise ValueError(f"panel sample cap must be >= 1 pixel, got {cap}")
    return [[ix[::max(1, -(-ix.numel() // cap))] for ix in per_cam] for per_cam in pixels]


def panel_regions(pixels: list[list[torch.Tensor]], panel_names: list[str], height: int, width: int,
                  camera: int = 0) -> dict[str, list[int]]:
    """An axis-aligned rectangle [y0, y1, x0, x1] (rows y0..y1-1, columns x0..x1-1) of each panel's interior
    pixels in one camera's image: the bounding box of the interior, shrunk from its emptiest side until every
    pixel inside is interior (for ELM from pixel regions, e.g. ``torchskin calibrate``), from the
    panels' interior ``pixels`` (``panel_pixels``) in an image of ``height`` x ``width``."""
    H, W = height, width
    out = {}
    for name, per_cam in zip(panel_names, pixels):
        flat = np.zeros(H * W, dtype=bool)
        flat[per_cam[camera].cpu().numpy()] = True
        m = flat.reshape(H, W)
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        while y1 > y0 and x1 > x0 and not m[y0:y1, x0:x1].all():
            sub = m[y0:y1, x0:x1]
            empty = [(~sub[0]).mean(), (~sub[-1]).mean(), (~sub[:, 0]).mean(), (~sub[:, -1]).mean()]
            k = int(np.argmax(empty))
            y0, y1, x0, x1 = y0 + (k == 0), y1 - (k == 1), x0 + (k == 2), x1 - (k == 3)
        out[name] = [y0, y1, x0, x1]
    return out


def panel_normals(gb: GBuffer, pixels: list[list[torch.Tensor]], camera: int = 0) -> torch.Tensor:
    """Unit normal (P, 3) of each reference panel (planes): the G-buffer's normal at the first of its interior
    ``pixels`` (``panel_pixels``) in camera ``camera``."""
    flat = gb.normal[camera].reshape(-1, 3)
    return torch.stack([flat[per_cam[camera][0]] for per_cam in pixels])


def panel_values(x: torch.Tensor, pixels: list[list[torch.Tensor]]) -> torch.Tensor:
    """Median of ``x`` (S, C, H, W, B) over each panel's interior pixels: (S, C, P, B)."""
    flat = x.flatten(2, 3)  # (S, C, H*W, B); medians along contiguous rows, (S, B, K): faster than along K of (S, K, B)
    return torch.stack([torch.stack([flat[:, c].index_select(1, ix).transpose(1, 2).contiguous().median(dim=-1).values
                                     for c, ix in enumerate(per_cam)], dim=1) for per_cam in pixels], dim=2)


def panel_references(panel_materials: list[int], gb: GBuffer, tables: MaterialTables, sun_dirs: torch.Tensor,
                     pix: list[list[torch.Tensor]], elm: str = "dhr") -> torch.Tensor:
    """Reference reflectance of each panel (S, C, P, B); ``panel_materials``: each panel's material id. ``elm="dhr"``: the panels' hemispherical
    reflectance (the usual ELM, eqs 2.5.5-2.5.6); ``elm="brdf"``: π f_BRDF of each panel at its pixels'
    source/view geometry (median over the interior), i.e. BRDF-ELM (eqs 3.3.1-3.3.3) in Lambertian-
    equivalent units (identical to "dhr" for Lambertian panels)."""
    if elm not in ("dhr", "brdf"):
        raise ValueError(f"elm must be 'dhr' or 'brdf', got {elm!r}")
    S, C = sun_dirs.shape[0], gb.hit.shape[0]
    HW = gb.hit[0].numel()
    out = []
    for k, m in enumerate(panel_materials):
        ref = tables.reference[m].expand(S, C, -1)
        group = next((g for g in tables.groups.values() if m in g.ids), None)
        if elm == "brdf" and group is not None:
            per_cam = []
            for c, ix in enumerate(pix[k]):
                ci, cr, c2b = pixel_cosines(gb, ix + c * HW, sun_dirs)
                f = group.brdf(ci, cr, c2b, gather_params(group.params, torch.full_like(ix, m)))  # (S, K, B)
                per_cam.append(math.pi * f.median(dim=1).values)
            ref = torch.stack(per_cam, dim=1)
        out.append(ref)
    return torch.stack(out, dim=2)


def apply_elm(signal: torch.Tensor, panel_signal: torch.Tensor, references: torch.Tensor) -> torch.Tensor:
    """Map signals (S, C, H, W, B) to reflectance with the line through the first two panels (eq 2.5.7)."""
    a, b = elm_coefficients(panel_signal[:, :, 0], panel_signal[:, :, 1], references[:, :, 0], references[:, :, 1])
    return elm_line(signal, a[:, :, None, None, :], b[:, :, None, None, :])


def panel_sunlit_fraction(lit: torch.Tensor, pixels: list[list[torch.Tensor]], camera: int = 0) -> list[float]:
    """Per reference panel, the sunlit share of its interior ``pixels`` (``panel_pixels``) in one frame's sunlit
    mask ``lit`` (H, W) of camera ``camera``."""
    flat = lit.reshape(-1)
    return [float(flat.index_select(0, per_cam[camera]).float().mean()) for per_cam in pixels]


def panel_median_noise_dn(panel_signal: torch.Tensor, pixels: TensorLike, read_noise_e: float, dn_per_e: float,
                          quantize: bool = True, noise: bool = True) -> torch.Tensor:
    """Standard deviation (DN) of a panel's median signal from the sensor noise model (``sensor.sensor_signal``):
    per pixel σ² = N_e + σ_read² electrons (shot and read noise) plus the ADC's 1/12 DN² with ``quantize``; the
    median of ``pixels`` such pixels has σ·sqrt(π/2)/sqrt(pixels) (the median's asymptotic efficiency for Gaussian
    noise); ``noise=False`` (a sensor without shot and read noise): the ADC's alone. ``panel_signal``: the medians (DN, any shape); ``pixels``: how many pixels each median took
    (broadcasting against ``panel_signal``); ``dn_per_e``: the ADC gain, 2^adc_bits / full_well_e.

    >>> s = panel_median_noise_dn(torch.tensor([10000.0]), 256, read_noise_e=50.0, dn_per_e=2**14 / 2e6)  # 9.1 DN a pixel
    >>> round(float(s), 3)
    0.71
    """
    L = as_tensor(panel_signal)
    n = as_tensor(pixels, like=L)
    electrons = L.clamp_min(0) / dn_per_e
    var_dn = (electrons + read_noise_e**2) * dn_per_e**2 * float(noise) + (1.0 / 12.0 if quantize else 0.0)
    return torch.sqrt(var_dn * (math.pi / 2) / n.clamp_min(1))


def elm_line_valid(panel_signal: torch.Tensor, references: torch.Tensor, noise_dn: torch.Tensor,
                   min_sigma: float = ELM_MIN_SEPARATION_SIGMA) -> torch.Tensor:
    """Whether the empirical line through the first two panels is a line, per frame: ``panel_signal``,
    ``references`` and ``noise_dn`` (the medians' σ, ``panel_median_noise_dn``) of shape (..., P, B) give a
    boolean (...). In every band:

    - the panels' signals are separated by at least ``min_sigma`` σ of their difference,
      ``abs(L2 - L1) >= min_sigma * sqrt(σ1² + σ2²)`` (``ELM_MIN_SEPARATION_SIGMA``);
    - the gain a = (L2 - L1) / (ρ2 - ρ1) is finite and positive (a brighter panel reads brighter), and the
      offset finite.

    Whether the line stands for the scene's light is ``panel_irradiance_ratio``'s question.

    >>> L = torch.tensor([[970.0, 30.0]])[..., None]  # one frame, panels 0.97 and 0.03, one band
    >>> refs = torch.tensor([[0.97, 0.03]])[..., None]
    >>> bool(elm_line_valid(L, refs, torch.full_like(L, 1.0)))  # 940 DN apart, σ of the difference 1.41 DN
    True
    >>> bool(elm_line_valid(L, refs, torch.full_like(L, 40.0)))  # 940 DN < 20 x 56.6 DN
    False
    """
    L1, L2 = panel_signal[..., 0, :], panel_signal[..., 1, :]
    r1, r2 = references[..., 0, :], references[..., 1, :]
    sigma = torch.sqrt(noise_dn[..., 0, :] ** 2 + noise_dn[..., 1, :] ** 2)
    a, b = _line(L1, L2, r1, r2)  # non-finite where the panels' references coincide: not a line
    ok = ((L2 - L1).abs() >= min_sigma * sigma) & torch.isfinite(a) & (a > 0) & torch.isfinite(b)
    return ok.all(dim=-1)


def panel_irradiance_ratio(beam: torch.Tensor, sky: torch.Tensor, sun_dirs: torch.Tensor,
                           panel_normals: torch.Tensor) -> torch.Tensor:
    """Per sun (S,), the most irradiance an unoccluded surface of any orientation receives from the sun and the
    sky, over the irradiance of the reference panels, the largest over panels and bands: how many times its
    reflectance a sunlit Lambertian surface can read through the empirical line (``ELM_MAX_IRRADIANCE_RATIO``).

    ``beam``, ``sky`` (S, B): the light tables' beam (on a surface facing the sun) and isotropic sky irradiance
    (on a level surface), as shading reads them (``LightTables``); ``sun_dirs`` (S, 3) unit vectors to the sun, z
    up; ``panel_normals`` (P, 3) unit normals. A surface of normal n receives E(n) = E_beam max(0, n·s) +
    E_sky (1 + n_z) / 2 (the isotropic sky's view factor), whose largest value over n, at n along
    v = E_beam s + (E_sky / 2) z, is E_sky / 2 + ‖v‖. Ground-reflected light and occlusion are left out
    of both (a level panel sees no ground). 1 under an overcast sky (no beam); 1 / cos θz for a clear sky and level
    panels; inf where a panel receives no light.

    >>> s = torch.tensor([[0.0, 0.0, 1.0], [0.8, 0.0, 0.6]], dtype=torch.float64)  # sun at the zenith; 53.1° off
    >>> up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    >>> beam = torch.tensor([[1.0], [1.0]], dtype=torch.float64)
    >>> [round(float(r), 6) for r in panel_irradiance_ratio(beam, torch.zeros_like(beam), s, up)]  # 1 / cos θz
    [1.0, 1.666667]
    >>> float(panel_irradiance_ratio(torch.zeros_like(beam), beam, s, up)[1])  # overcast: every surface alike
    1.0
    """
    cz = sun_dirs[:, 2:3]  # (S, 1)
    e_max = sky / 2 + torch.sqrt(beam**2 + beam * sky * cz + sky**2 / 4)  # (S, B)
    n = panel_normals.to(beam)
    cos_p = (sun_dirs.to(beam) @ n.T).clamp_min(0)  # (S, P)
    e_panel = beam[:, None, :] * cos_p[..., None] + sky[:, None, :] * ((1 + n[:, 2]) / 2)[None, :, None]
    ratio = torch.where(e_panel > 0, e_max[:, None, :] / e_panel.clamp_min(torch.finfo(beam.dtype).tiny),
                        torch.full_like(e_panel, math.inf))
    return ratio.amax(dim=(1, 2))
