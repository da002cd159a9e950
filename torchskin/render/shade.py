"""Stage 4 of the renderer: G-buffer + material tables + suns -> at-surface radiance (W m^-2 sr^-1 nm^-1).

Shapes: S suns (or N = K·S skin-major rows for a batch of K skins), C cameras, H x W pixels, B bands.

>>> import torch
>>> from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun
>>> from torchskin.render.raycast import rasterize
>>> from torchskin.render.materials import compile_materials
>>> sc = Scene({"grey": Material(reflectance=0.5)}, [MeshSpec("wall", "plane", "grey", {"width": 9, "height": 9},
...            position=[0, 0, -4])], [Camera(width=8, height=8, zenith_deg=90)], [Sun(zenith_deg=60)], panels=[])
>>> gb = rasterize(sc)
>>> t = compile_materials(sc.materials, sc.bands, sc.suns, gb.material_names)
>>> L = shade(gb, t, torch.tensor(sc.suns[0].direction[None], dtype=torch.float32), torch.zeros(1)).radiance
>>> ratio = L[0, 0, 4, 4] / (t.irradiance[0] * 0.5 / torch.pi)  # Lambertian: E cos θi ρ / π, cos θi = sin 60°
>>> [round(float(x), 4) for x in ratio]
[0.866, 0.866, 0.866, 0.866]
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .kernels import KERNELS, brdf_radiance, lambert_sky, local_cosines
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


def shade(gb: GBuffer, tables: MaterialTables, sun_dirs: torch.Tensor, sky_fraction: torch.Tensor,
          dense: bool | None = None, sky_background: bool = False, compile: bool = False) -> Shading:
    """At-surface radiance (S, C, H, W, B), W m^-2 sr^-1 nm^-1, and the sunlit mask (S, C, H, W).

    Args:
        gb: the G-buffer (``raycast.rasterize``), its shadow masks one per row of ``sun_dirs``.
        tables: the compiled materials (``materials.compile_materials``) in ``gb.material_names`` order.
        sun_dirs: (S, 3) unit vectors towards each sun; ``sky_fraction`` (S,): each sun's sky irradiance on a
            horizontal surface relative to its normal irradiance.

    Sunlit: L = f(θi, θr, Δφ) E cos θi, with f the BRDF of each material's kind (the combined skin BRDF of eq
    3.1.1, the Spectralon-like panel, ...) on its pixels (``kernels.brdf_radiance``) and albedo/π for Lambertian
    kinds; plus a uniform sky on every hit pixel,
    ρ_hemi/π · E_sky · (1 + n_z)/2. On the CPU the skin (and panel) BRDF is evaluated on its pixels only
    (gathered); with ``dense`` (the default on accelerators) on every pixel and selected, so that shading
    waits for no data-dependent pixel count (no host round trip). ``sky_background``: rays that hit nothing
    and point above the horizon see the uniform sky itself, radiance sky_fraction · E / π (the dome whose
    irradiance on a horizontal surface is sky_fraction · E); otherwise missed rays carry no radiance.
    ``compile``: the shading every material shares (``kernels.lambert_sky``) and each BRDF kind's term
    (``kernels.brdf_radiance``) as fused compiled kernels.
    """
    shp = gb.hit.shape  # (C, H, W)
    S = sun_dirs.shape[0]
    n = gb.normal.reshape(-1, 3)
    hit = gb.hit.reshape(-1)
    mat = gb.material.reshape(-1).clamp_min(0)
    E = tables.irradiance[:, None, :]  # (S, 1, B)
    L, lit, w = KERNELS.get(lambert_sky, compile, n.device)(
        n, hit, mat, gb.shadow_masks().reshape(S, -1), sun_dirs, sky_fraction, tables.irradiance, tables.albedo,
        tables.lambert_f, gb.rays.reshape(-1, 6)[:, 5], sky_background)
    if dense is None:
        dense = n.device.type != "cpu"
    dirs = gb.rays.reshape(-1, 6)[:, 3:]
    for group in tables.groups.values():  # BRDF kinds carry no Lambertian part (lambert_f = 0): add f E cos θi
        kernel = KERNELS.get(brdf_radiance, compile, n.device)
        if dense:  # every pixel, then selected: no data-dependent pixel count (no host round trip)
            sel = (hit & group.member[mat])[:, None]
            L = torch.where(sel, kernel(group.brdf, gather_params(group.params, mat), n, dirs, sun_dirs, L, w, E), L)
            continue
        idx = (hit & group.member[mat]).nonzero().flatten()
        if idx.numel():
            L.index_copy_(1, idx, kernel(group.brdf, gather_params(group.params, mat.index_select(0, idx)),
                                         n.index_select(0, idx), dirs.index_select(0, idx), sun_dirs,
                                         L.index_select(1, idx), w.index_select(1, idx), E))
    B = L.shape[-1]
    return Shading(L.reshape(S, *shp, B), lit.reshape(S, *shp))
