"""Stage 4 of the renderer: G-buffer + material tables + light tables -> at-surface radiance (W m^-2 sr^-1 nm^-1).

Shapes: S suns (or N = K·S skin-major rows for a batch of K skins), C cameras, H x W pixels, B bands.

>>> import torch
>>> from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun
>>> from torchskin.render.raycast import rasterize
>>> from torchskin.render.materials import compile_materials
>>> from torchskin.render.light import light_tables
>>> sc = Scene({"grey": Material(reflectance=0.5)}, [MeshSpec("wall", "plane", "grey", {"width": 9, "height": 9},
...            position=[0, 0, -4])], [Camera(width=8, height=8, zenith_deg=90)], [Sun(zenith_deg=60)], panels=[],
...            illumination="thesis")
>>> gb = rasterize(sc)
>>> t = compile_materials(sc.materials, sc.bands, sc.suns, gb.material_names)
>>> light = light_tables(sc.illumination, sc.suns, sc.bands, torch.float32)
>>> L = shade(gb, t, light, torch.tensor(sc.suns[0].direction[None], dtype=torch.float32)).radiance
>>> ratio = L[0, 0, 4, 4] / (light.beam[0] * 0.5 / torch.pi)  # Lambertian: E cos θi ρ / π, cos θi = sin 60°
>>> [round(float(x), 4) for x in ratio]
[0.866, 0.866, 0.866, 0.866]
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .kernels import KERNELS, brdf_kernel, cos_to, lambert_sky, local_cosines, pad_rows
from .light import LightTables
from .materials import MaterialTables
from .raycast import GBuffer


@dataclass
class Shading:
    """``radiance`` (S, C, H, W, B), W m^-2 sr^-1 nm^-1, and ``lit`` (S, C, H, W): sunlit (facing the sun, hit,
    not in a cast shadow)."""

    radiance: torch.Tensor
    lit: torch.Tensor


def pixel_cosines(gb: GBuffer, idx: torch.Tensor,
                  sun_dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """cos θi (S, K, 1, clamped at 0), cos θr (1, K, 1) and cos 2β = ω_i·ω_r (S, K, 1) at flat pixels ``idx``
    (``kernels.local_cosines``)."""
    return local_cosines(gb.normal.reshape(-1, 3).index_select(0, idx),
                         gb.rays.reshape(-1, 6).index_select(0, idx)[:, 3:], sun_dirs)


def gather_params(params: dict[str, torch.Tensor], material: torch.Tensor) -> dict[str, torch.Tensor]:
    """A BRDF group's parameters at pixels of material ids ``material`` (K,): each ([N,] M, X) -> ([N,] K, X);
    parameters shared by the whole group, (X,), stay as they are."""
    return {k: v if v.dim() == 1 else v.index_select(-2, material) for k, v in params.items()}


def diffuse_views(gb: GBuffer, tables: MaterialTables, light: LightTables) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel (N,): the cosine-weighted view of the sky, and (N, B) of up-facing surfaces weighted by their
    hemispherical reflectance (``tables.reference``): what the sky and ground tables of ``light`` reach it with
    (zeros when the light has neither; ValueError when it needs them and the G-buffer has no sky view)."""
    n = gb.hit.numel()
    dtype, device = gb.normal.dtype, gb.normal.device
    if not light.needs_sky_view:
        return torch.zeros(n, dtype=dtype, device=device), torch.zeros(n, tables.reference.shape[-1], dtype=dtype,
                                                                        device=device)
    sky, ground = gb.sky_views()
    # (N, M) view fractions times (M, B) reflectance: a short sum, in float64 and rounded once (the same bits for any
    # summation order)
    refl = (ground.reshape(n, -1).double() @ tables.reference.double()).to(dtype)
    return sky.reshape(-1), refl


def irradiance(gb: GBuffer, tables: MaterialTables, light: LightTables, sun_dirs: torch.Tensor,
               lit: torch.Tensor, bands: list[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The irradiance each pixel receives in the bands ``bands`` (indices; None: all), (S, N, B') twice,
    W m^-2 nm^-1: ``direct``, the beam (direct sun and circumsolar sky) E_beam cos θi where ``lit`` (S, ...)
    (sunlit: ``Shading.lit``), and ``diffuse``, the isotropic sky and the ground-reflected light it sees,
    E_sky V_sky + E_ground Σ_m V_m ρ_m (as ``shade`` lights it)."""
    n = gb.normal.reshape(-1, 3)
    cos_i = cos_to([n[:, 0], n[:, 1], n[:, 2]], sun_dirs).clamp_min(0) * lit.reshape(lit.shape[0], -1)
    sky_view, ground_view = diffuse_views(gb, tables, light)
    hit = gb.hit.reshape(-1)
    pick = slice(None) if bands is None else torch.tensor(bands, device=n.device)
    beam, sky, ground = light.beam[:, pick], light.sky[:, pick], light.ground[:, pick]
    direct = beam[:, None, :] * cos_i[..., None]
    diffuse = (sky[:, None, :] * sky_view[:, None] + ground[:, None, :] * ground_view[:, pick]) * hit[:, None]
    return direct, diffuse


def shade(gb: GBuffer, tables: MaterialTables, light: LightTables, sun_dirs: torch.Tensor,
          dense: bool | None = None, sky_background: bool = False, compile: bool = False) -> Shading:
    """At-surface radiance (S, C, H, W, B), W m^-2 sr^-1 nm^-1, and the sunlit mask (S, C, H, W).

    Args:
        gb: the G-buffer (``raycast.rasterize``), its shadow masks one per row of ``sun_dirs``, and its sky view
            (``Raycaster.with_sky_view``) when ``light`` has sky or ground light.
        tables: the compiled materials (``materials.compile_materials``) in ``gb.material_names`` order.
        light: the light tables (``light.light_tables``; rows as ``sun_dirs``): beam, sky and ground per band.
        sun_dirs: (S, 3) unit vectors towards each sun.

    Sunlit: L = f(θi, θr, Δφ) E_beam cos θi, with f the BRDF of each material's kind (the combined skin BRDF of eq
    3.1.1, the Spectralon-like panel, ...) on its pixels (``kernels.brdf_radiance``) and albedo/π for Lambertian
    kinds; plus, on every hit pixel, the sky and the ground it sees (``kernels.lambert_sky``):
    ρ_hemi/π · (E_sky V_sky + E_ground Σ_m V_m ρ_m). On the CPU the skin (and panel) BRDF is evaluated on its
    pixels only (gathered); with ``dense`` (the default on accelerators) on every pixel and selected, so that
    shading waits for no data-dependent pixel count (no host round trip). ``sky_background``: rays that hit
    nothing and point above the horizon see the isotropic sky itself, radiance E_sky / π; otherwise missed rays
    carry no radiance. ``compile``: the shading every material shares and each BRDF kind's term
    (``kernels.brdf_radiance``) as fused compiled kernels.
    """
    shp = gb.hit.shape  # (C, H, W)
    S = sun_dirs.shape[0]
    n = gb.normal.reshape(-1, 3)
    hit = gb.hit.reshape(-1)
    mat = gb.material.reshape(-1).clamp_min(0)
    E = light.beam[:, None, :]  # (S, 1, B)
    sky_view, ground_view = diffuse_views(gb, tables, light)
    L, lit, w = KERNELS.get(lambert_sky, compile, n.device)(
        n, hit, mat, gb.shadow_masks().reshape(S, -1), sun_dirs, light.beam, light.sky, light.ground, sky_view,
        ground_view, pad_rows(tables.albedo), pad_rows(tables.lambert_f), gb.rays.reshape(-1, 6)[:, 5],
        sky_background)
    if dense is None:
        dense = n.device.type != "cpu"
    dirs = gb.rays.reshape(-1, 6)[:, 3:]
    for group in tables.groups.values():  # BRDF kinds carry no Lambertian part (lambert_f = 0): add f E cos θi
        kernel = KERNELS.get(brdf_kernel(group.brdf), compile, n.device)
        if dense:  # every pixel, then selected: no data-dependent pixel count (no host round trip)
            sel = (hit & group.member[mat])[:, None]
            L = torch.where(sel, kernel(gather_params(group.params, mat), n, dirs, sun_dirs, L, w, E), L)
            continue
        idx = (hit & group.member[mat]).nonzero().flatten()
        k = idx.numel()
        if k:
            # compiled: a group of <= 16 pixels is padded to 17 (its last pixel repeated), so that its pixel axis
            # stays dynamic (``compiled.mark_dynamic``) and a small group does not compile a kernel of its own
            take = torch.cat([idx, idx[-1:].expand(17 - k)]) if compile and k <= 16 else idx
            L.index_copy_(1, idx, kernel(gather_params(group.params, mat.index_select(0, take)),
                                         n.index_select(0, take), dirs.index_select(0, take), sun_dirs,
                                         L.index_select(1, take), w.index_select(1, take), E)[:, :k])
    B = L.shape[-1]
    return Shading(L.reshape(S, *shp, B), lit.reshape(S, *shp))
