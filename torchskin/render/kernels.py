"""The renderer's per-pixel hot paths, written once and run either eagerly or as fused ``torch.compile`` kernels
(Inductor: C++/OpenMP on the CPU, Triton on CUDA).

Each kernel is a plain torch function of static structure: gathers by index up front, then arithmetic on
(N,)-shaped components (x, y, z written out, no matmuls), so that Inductor fuses the whole function into one
loop over the pixels instead of one pass over memory per operation. ``KERNELS.get(fn, compile=True)`` returns
the compiled form (pixel axes marked dynamic: one compilation serves every frame size; component and band
axes stay static so that the loops vectorise); ``compile=False`` returns ``fn``
itself, the reference and the fallback. Compilation falls back to ``fn`` (with one warning) when no compiler
is present or Inductor fails.

Random draws never happen inside a kernel: noise is drawn eagerly with the caller's generator and passed in,
so a seed gives the same noise whichever path runs.

The compiled forms live in the package's one kernel cache, ``compiled.KERNELS`` (``KernelCache``, shared with the
skin model's hot loop). Inductor keeps compiled kernels on disk between runs (``devices.inductor_cache_dir``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path

import torch

from ..compiled import KERNELS  # noqa: F401 - re-exported: the renderer's stages take the one cache from here
from ..detect import RulesBox, normalized_difference, rules_detector
from ..devices import compiler_problem, inductor_cache_dir


def cache_dir() -> Path:
    """Where Inductor keeps compiled kernels between runs (``devices.inductor_cache_dir``)."""
    return Path(inductor_cache_dir())


def compiler_available(device: torch.device | str = "cpu") -> bool:
    """Whether ``torch.compile`` kernels are used for ``device`` (``devices.compiler_problem`` is None: a C++
    compiler and a validated CPU capability on the CPU, Triton on CUDA, Metal on MPS)."""
    return compiler_problem(device) is None


#: lookup tables whose length follows the scene's content (meshes, materials) are padded to a multiple of this
#: (``table_rows``): longer than ``mark_dynamic``'s 16, so that the compiled kernels take every scene's tables
#: without recompiling
TABLE_ROWS = 32


def table_rows(n: int) -> int:
    """``n`` rounded up to a multiple of ``TABLE_ROWS`` (at least one multiple)."""
    return max(TABLE_ROWS, -(-n // TABLE_ROWS) * TABLE_ROWS)


def pad_rows(x: torch.Tensor, dim: int = -2) -> torch.Tensor:
    """``x`` with zeros appended along ``dim`` up to ``table_rows`` rows (itself when already that long): per-material
    tables handed to a compiled kernel, whose unused rows no pixel indexes."""
    n = x.shape[dim]
    extra = table_rows(n) - n
    if extra == 0:
        return x
    shape = list(x.shape)
    shape[dim] = extra
    return torch.cat([x, x.new_zeros(shape)], dim)


def point_along(origin: torch.Tensor, direction: torch.Tensor, distance: torch.Tensor | float) -> torch.Tensor:
    """origin + distance · direction: a hit position along a ray, a shadow-ray origin off a surface."""
    return origin + distance * direction


def cos_to(normal: list[torch.Tensor] | torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """n·ω (S, N) of N normals (three (N,) components, or (N, 3)) with S unit directions (S, 3), written out
    component by component: the same bits for any thread count, BLAS or CPU (a matrix product's summation
    order is the library's choice, and a facing test on its last bit is not reproducible)."""
    n = normal if isinstance(normal, list) else list(normal.unbind(-1))
    return dirs[:, 0:1] * n[0] + dirs[:, 1:2] * n[1] + dirs[:, 2:3] * n[2]


def aperture_radiance(radiance: torch.Tensor, path: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """Radiance at the aperture, τ L + L_path (eq 2.5.1)."""
    return torch.addcmul(path, tau, radiance)


def gbuffer_fields(rays: torch.Tensor, t: torch.Tensor, geometry_ids: torch.Tensor, primitive_ids: torch.Tensor,
                   uvs: torch.Tensor, primitive_normals: torch.Tensor, face_offset: torch.Tensor,
                   corner_normals: torch.Tensor, face_material: torch.Tensor, geometry_mesh: torch.Tensor,
                   sun_dirs: torch.Tensor, facing_margin: float, shadow_offset: float
                   ) -> tuple[torch.Tensor, ...]:
    """Per pixel from open3d's ray-cast answers (N rays): hit, smooth normal, geometric normal (both turned to
    the viewer), material id, mesh id, (S, N) whether each pixel is hit and faces
    each sun (n·ω_sun > -``facing_margin``), the shadow-ray origin (N, 3), ``shadow_offset`` off the surface
    along the geometric normal, and the hit face (N,) (over all meshes; the sentinel face at misses).

    ``rays`` (N, 6); ``t`` (N,); ``geometry_ids``, ``primitive_ids`` (N,) int32 (-1: no hit); ``uvs`` (N, 2);
    ``primitive_normals`` (N, 3); tables indexed by geometry id + 1 (``face_offset``, ``geometry_mesh``) or by
    face (``corner_normals`` (F+1, 9): the vertex normals of each face's three corners; ``face_material``),
    the last face a sentinel for misses; ``sun_dirs`` (S, 3).
    """
    hit = torch.isfinite(t)
    gid1 = geometry_ids.long() + 1
    face = face_offset[gid1] + primitive_ids.long().clamp_min(0)
    u, v = uvs[:, 0], uvs[:, 1]
    w0 = 1 - u - v
    cn = corner_normals.index_select(0, face)  # one row gather (fast eagerly; fused when compiled)
    corner = [cn[:, k] for k in range(9)]
    n = [w0 * corner[k] + u * corner[3 + k] + v * corner[6 + k] for k in range(3)]
    d = [rays[:, 3 + k] for k in range(3)]
    g = [primitive_normals[:, k] for k in range(3)]
    # two-sided surfaces: both normals on the viewer's side of the triangle
    side = torch.where(g[0] * d[0] + g[1] * d[1] + g[2] * d[2] > 0, -1.0, 1.0).to(t.dtype)
    g = [x * side for x in g]
    scale = side / (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().clamp_min(1e-12)
    n = [x * scale for x in n]
    pos = [point_along(rays[:, k], d[k], t) for k in range(3)]
    facing = (cos_to(n, sun_dirs) > -facing_margin) & hit  # (S, N)
    origin = torch.stack([point_along(pos[k], g[k], shadow_offset) for k in range(3)], -1)
    return (hit, torch.stack(n, -1), torch.stack(g, -1), face_material[face], geometry_mesh[gid1], facing, origin,
            face)


def lambert_sky(normal: torch.Tensor, hit: torch.Tensor, material: torch.Tensor, shadow: torch.Tensor,
                sun_dirs: torch.Tensor, beam: torch.Tensor, sky: torch.Tensor, ground: torch.Tensor,
                sky_view: torch.Tensor, ground_view: torch.Tensor, albedo: torch.Tensor, lambert_f: torch.Tensor,
                ray_dz: torch.Tensor, sky_background: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The shading every material shares, per sun, pixel and band: the diffuse light on every hit pixel,
    ρ_hemi/π · (E_sky V_sky + E_ground R_ground), plus the Lambertian part f E_beam cos θi on sunlit pixels;
    and, with ``sky_background``, the sky's own radiance E_sky / π on missed rays that climb (``ray_dz`` > 0, the
    camera rays' z direction).

    ``normal`` (N, 3); ``hit``, ``material`` (N,); ``shadow`` (S, N); ``sun_dirs`` (S, 3); ``beam``, ``sky``,
    ``ground`` (S, B): the light tables (``light.LightTables``); ``sky_view`` (N,): the pixel's cosine-weighted view
    of the sky; ``ground_view`` (N, B): its view of up-facing surfaces weighted by their reflectance (the light
    they reflect per unit of ``ground``); ``albedo``, ``lambert_f`` ([S,] M, B) by material.

    Returns:
        radiance (S, N, B), sunlit mask (S, N) and sunlit cos θi (S, N) (0 where not sunlit).
    """
    cos_i = cos_to([normal[:, 0], normal[:, 1], normal[:, 2]], sun_dirs)  # (S, N)
    lit = (cos_i > 0) & ~shadow & hit
    w = torch.where(lit, cos_i, torch.zeros((), dtype=cos_i.dtype, device=cos_i.device))
    E = beam[:, None, :]  # (S, 1, B)
    diffuse = sky[:, None, :] * (sky_view * hit)[:, None] + ground[:, None, :] * ground_view  # (S, N, B)
    L = torch.addcmul(albedo.index_select(-2, material) * diffuse * (1 / math.pi), w[..., None],
                      lambert_f.index_select(-2, material) * E)
    if sky_background:
        up = ~hit & (ray_dz > 0)  # the ray climbs
        L = torch.where(up[:, None], sky[:, None, :] * (1 / math.pi), L)
    return L, lit, w


def band_tiles(x: torch.Tensor, per_image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int]:
    """A (S, C, ..., B) frame as (S·C, rows, R) with R = k·B (k pixels of B bands; R at most 16 when B <= 16,
    k dividing the pixels per image) and per-image, per-band constants ``per_image`` ((S, C, B) or (B,)) tiled
    to (S·C or 1, 1, R): a fused kernel then runs along R in full vector lanes instead of along 4 bands.
    Returns (view, tiled constants, k); ``tile(c, k)`` tiles more (B,) constants."""
    S, C, B = x.shape[0], x.shape[1], x.shape[-1]
    pixels = x[0, 0].numel() // B
    k = next(k for k in range(max(1, 16 // B), 0, -1) if pixels % k == 0)
    rows = S * C if per_image.dim() == 3 else 1
    return x.reshape(S * C, -1, k * B), per_image.reshape(rows, 1, B).repeat(1, 1, k), k


def tile(c: torch.Tensor, k: int) -> torch.Tensor:
    """(B,) per-band constants repeated k times: (k·B,), the layout of ``band_tiles``."""
    return c.repeat(k)


def local_cosines(normal: torch.Tensor, ray_dirs: torch.Tensor,
                  sun_dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """cos θi (S, K, 1, clamped at 0), cos θr (1, K, 1) and cos 2β = ω_i·ω_r (S, K, 1) of K pixels with unit
    normals ``normal`` (K, 3) seen along camera rays ``ray_dirs`` (K, 3) (the view vector is their opposite),
    under suns ``sun_dirs`` (S, 3)."""
    n, v = [normal[:, k] for k in range(3)], [-ray_dirs[:, k] for k in range(3)]
    ci = sun_dirs[:, 0:1] * n[0] + sun_dirs[:, 1:2] * n[1] + sun_dirs[:, 2:3] * n[2]
    cr = n[0] * v[0] + n[1] * v[1] + n[2] * v[2]
    c2b = sun_dirs[:, 0:1] * v[0] + sun_dirs[:, 1:2] * v[1] + sun_dirs[:, 2:3] * v[2]
    return ci.clamp_min(0)[..., None], cr[None, :, None], c2b[..., None]


def brdf_radiance(brdf: Callable, params: dict[str, torch.Tensor], normal: torch.Tensor, ray_dirs: torch.Tensor,
                  sun_dirs: torch.Tensor, radiance: torch.Tensor, sunlit_cos: torch.Tensor,
                  irradiance: torch.Tensor) -> torch.Tensor:
    """``radiance`` (S, K, B) of K pixels of one BRDF kind plus its sunlit term f(θi, θr, Δφ) E cos θi, with
    ``sunlit_cos`` (S, K) the cosine where sunlit (else 0), ``irradiance`` (S, 1, B) and ``brdf(ci, cr, c2b,
    params)`` the kind's BRDF (``materials.MaterialKind``) with its parameters at the pixels."""
    ci, cr, c2b = local_cosines(normal, ray_dirs, sun_dirs)
    return torch.addcmul(radiance, sunlit_cos[..., None] * irradiance, brdf(ci, cr, c2b, params))


@functools.cache
def brdf_kernel(brdf: Callable) -> Callable:
    """``brdf_radiance`` with the BRDF ``brdf`` bound, as a kernel of its own (one per BRDF kind, named after it):
    each kind compiles once into its own kernel instead of recompiling one shared kernel whenever another kind
    comes next."""

    def kernel(params: dict[str, torch.Tensor], normal: torch.Tensor, ray_dirs: torch.Tensor, sun_dirs: torch.Tensor,
               radiance: torch.Tensor, sunlit_cos: torch.Tensor, irradiance: torch.Tensor) -> torch.Tensor:
        return brdf_radiance(brdf, params, normal, ray_dirs, sun_dirs, radiance, sunlit_cos, irradiance)

    name = getattr(brdf, "__qualname__", type(brdf).__name__)
    kernel.__name__ = f"brdf_radiance[{name}]"
    kernel.__qualname__ = f"brdf_radiance[{getattr(brdf, '__module__', '')}.{name}]"
    return kernel


def sensor_dn(radiance: torch.Tensor, path: torch.Tensor, tau: torch.Tensor, gain: torch.Tensor,
              noise: torch.Tensor | None, dn_per_e: torch.Tensor, read_noise_dn2: torch.Tensor, levels: int,
              atmosphere: bool, quantize: bool) -> torch.Tensor:
    """Digital numbers from at-surface radiance (eq 2.5.2 after the exposure): L_aperture = τ L + L_path (with
    ``atmosphere``), DN = L_aperture · ``gain``; plus shot and read noise, σ² = DN·g + σ_read² (DN², g =
    ``dn_per_e``) times the standard-normal draw ``noise`` (None: no noise); then the ADC: rounded and clipped
    to [0, levels - 1] with ``quantize``, else clipped to [0, levels]. ``dn_per_e`` and ``read_noise_dn2`` are
    0-d tensors, inputs of a compiled kernel rather than constants baked into it (a new read noise would
    recompile it)."""
    L = aperture_radiance(radiance, path, tau) if atmosphere else radiance
    dn = L * gain
    if noise is not None:
        dn = dn.addcmul(dn.clamp_min(0).mul(dn_per_e).add(read_noise_dn2).sqrt(), noise)
    if quantize:
        return torch.round(dn).clamp(0, levels - 1)
    return dn.clamp(0, levels * 1.0)


def elm_line(signal: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Reflectance from signal on the empirical line L = a ρ + b (eq 2.5.7): (L - b) / a."""
    inv_a = 1 / a
    return torch.addcmul(-b * inv_a, signal, inv_a)


def elm_indices(signal: torch.Tensor, a: torch.Tensor, b: torch.Tensor, bands: int, pick: tuple[int, int, int, int],
                box: RulesBox) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """ELM reflectance (``elm_line``) of a signal with ``bands`` bands innermost (any layout, e.g. ``band_tiles``),
    then per pixel NDGRI and NDSI from the bands at ``pick`` (544, 633, 1080, 1580 nm:
    ``detect.index_band_positions``) and the rules detector's verdict, in one pass; the per-pixel results are
    flat (pixels,)."""
    refl = elm_line(signal, a, b)
    px = refl.reshape(-1, bands)
    green, red, nir, swir = (px[:, i] for i in pick)
    g, s = normalized_difference(green, red), normalized_difference(nir, swir)
    return refl, g, s, rules_detector(g, s, box)
