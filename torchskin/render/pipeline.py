"""The renderer's stages called in order: scene -> meshes -> ray cast (G-buffer, shadows, sky view) -> materials
and light -> shading -> sensor -> ELM -> NDGRI/NDSI rules. ``render`` gives whole frames, ``render_pixels`` chosen pixels of one camera
(the dataset generator's fast path); both run the same stages (``render_gbuffer``).

Shapes: S suns (S·K skin-major rows for a batch of K skins), C cameras, H x W pixels, B bands; images are
``(S, C, H, W, B)``. Everything after the G-buffer runs on the requested device and dtype, without Python loops
over pixels.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any, cast

import numpy as np
import torch

from .. import tissue
from ..bands import Band
from ..detect import DEFAULT_BOX, RulesBox, has_index_bands, index_band_positions
from .elm import apply_elm, elm_coefficients, panel_references, panel_values
from .elm import panel_pixels as find_panel_pixels
from .kernels import KERNELS, band_tiles, elm_indices
from .light import LightTables, check_light, light_tables
from .materials import SHARED_CACHE, MaterialCache, MaterialTables, check_materials, compile_materials, skin_batch
from .raycast import GBuffer, Raycaster
from .scene import Scene
from .sensor import Sensor, sensor_signal
from .shade import irradiance as shade_irradiance
from .shade import shade


@dataclass
class RenderResult:
    """Everything a render produced. Shape: images (S, C, H, W[, B]) (``render_pixels``: (S, 1, 1, K[, B]))."""

    radiance: torch.Tensor  # at-surface radiance, W m^-2 sr^-1 nm^-1
    light: LightTables  # the light model's tables the frame was shaded with (rows as the images' leading axis)
    signal: torch.Tensor  # DN (or radiance without a sensor)
    reflectance: torch.Tensor  # ELM-calibrated
    ndgri: torch.Tensor  # (S, C, H, W)
    ndsi: torch.Tensor
    mask: torch.Tensor  # rules detector
    skin: torch.Tensor  # (C, H, W) ground truth: skin pixels
    lit: torch.Tensor  # (S, C, H, W) sunlit
    panels: dict  # per reference panel: "reference" and "signal" (S x C x B lists)
    gbuffer: GBuffer
    timing: dict
    bands: tuple[Band, ...]
    panel_pixels: list  # [panel][camera] flat interior pixel indices (``elm.panel_pixels``)
    #: with ``irradiance`` (band indices): the (direct, diffuse) irradiance each pixel receives in those bands,
    #: each (S, C, H, W, B'), W m^-2 nm^-1 (``shade.irradiance``)
    irradiance: tuple[torch.Tensor, torch.Tensor] | None = None

    def cube(self, s: int = 0, c: int = 0, what: str = "reflectance") -> np.ndarray:
        """Frame (sun ``s``, camera ``c``) of ``what`` ("reflectance", "signal" or "radiance") as a (B, H, W)
        float32 numpy cube: the layout of ``reflectance.npy`` and of the onboard runtime (add a leading batch
        axis for ``onboard``'s detector)."""
        if what not in ("reflectance", "signal", "radiance"):
            raise ValueError(f"what must be 'reflectance', 'signal' or 'radiance', got {what!r}")
        return getattr(self, what)[s, c].permute(2, 0, 1).contiguous().cpu().float().numpy()


#: ``render_pixels`` renders a multiple of this many pixels (the requested ones, the panels', then copies of the
#: first requested pixel), so that per-band kernels tile the pixels x bands in full vector lanes
PIXEL_MULTIPLE = 16
#: ``render``'s ways to find each pixel's view of the sky (``Raycaster.with_sky_view``'s methods)
SKY_VIEW_METHODS = ("field", "rays")


def sync(device: torch.device) -> None:
    """Wait for queued device work (for stage timings)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


def geometry(scene: Scene, raycaster: Raycaster | None, gbuffer: GBuffer | None, timing: dict,
             compile: bool = False, shadows: bool = True) -> tuple[GBuffer, Raycaster | None]:
    """The scene's G-buffer: ``gbuffer`` if given, else a ray cast (with ``raycaster``, or one built now); and
    the ray caster (None when ``gbuffer`` came without one). ``shadows=False`` leaves a fresh G-buffer's shadow
    masks to be cast later."""
    if gbuffer is not None:
        return gbuffer, raycaster
    t0 = time.perf_counter()
    if raycaster is None:
        raycaster = Raycaster.from_scene(scene)
        timing["build_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    gb = raycaster.gbuffer(scene.cameras, np.stack([s.direction for s in scene.suns]), compile, shadows)
    timing["raycast_s"] = time.perf_counter() - t1
    return gb, raycaster


def check_sky_view(sky_view: str) -> None:
    """ValueError unless ``sky_view`` is one of ``SKY_VIEW_METHODS``."""
    if sky_view not in SKY_VIEW_METHODS:
        raise ValueError(f"sky_view must be one of {', '.join(SKY_VIEW_METHODS)}, got {sky_view!r}")


def cast_shadows(scene: Scene, gb: GBuffer, raycaster: Raycaster | None, light: LightTables | None = None,
                 shared: Sequence[torch.Tensor] = (), sky_view: str = "field") -> GBuffer:
    """``gb`` with shadow masks (itself if it has them, else cast with ``raycaster`` for the scene's suns) and,
    when ``light`` has sky or ground light, its sky view (``Raycaster.with_sky_view`` by the method ``sky_view``;
    ``shared``: pixel groups that share one view, the reference panels' interiors)."""
    check_sky_view(sky_view)
    need_sky = light is not None and light.needs_sky_view and gb.sky is None
    if gb.shadow is not None and not need_sky:
        return gb
    if raycaster is None:
        what = "shadow masks" if gb.shadow is None else "sky view"
        raise ValueError(f"the G-buffer has no {what}: pass the raycaster that made it to cast them")
    if gb.shadow is None:
        gb = raycaster.with_shadows(gb.to("cpu", torch.float32), np.stack([s.direction for s in scene.suns]))
    return raycaster.with_sky_view(gb.to("cpu", torch.float32), shared=shared, method=sky_view) if need_sky else gb


def gather_pixels(gb: GBuffer, flat: torch.Tensor) -> GBuffer:
    """A G-buffer of the pixels ``flat`` (indices into the single camera's H*W), shaped (1, 1, K)."""
    if gb.hit.shape[0] != 1:
        raise ValueError("pixel subsets need a single camera")
    out: dict[str, Any] = {}
    for f in fields(gb):
        v = getattr(gb, f.name)
        if f.name == "shadow" and v is not None:
            out[f.name] = v.flatten(1).index_select(1, flat).reshape(v.shape[0], 1, 1, -1)
        elif isinstance(v, torch.Tensor):
            tail = v.shape[3:]
            out[f.name] = v.reshape(-1, *tail).index_select(0, flat).reshape(1, 1, -1, *tail)
        else:
            out[f.name] = v
    return GBuffer(**out)


def material_tables(scene: Scene, gb: GBuffer, dtype: torch.dtype, device: torch.device,
                    skins: tissue.SkinParams | None, cache: MaterialCache | None) -> MaterialTables:
    """The scene's materials compiled in the G-buffer's material order, through ``cache`` (default:
    ``materials.SHARED_CACHE``; batches of skins are compiled directly)."""
    if skins is None:
        cache = SHARED_CACHE if cache is None else cache
        return cache.compile(scene.materials, scene.bands, scene.suns, gb.material_names, dtype, device,
                             illumination=scene.illumination)
    return compile_materials(scene.materials, scene.bands, scene.suns, gb.material_names, dtype, device, skins,
                             illumination=scene.illumination)


def scene_light(scene: Scene, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> LightTables:
    """The light tables of ``scene`` (its light model, suns and bands: ``light.light_tables``)."""
    return light_tables(scene.illumination, scene.suns, scene.bands, dtype, device)


def render(scene: Scene, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
           sensor: Sensor | None = None, box: RulesBox = DEFAULT_BOX, raycaster: Raycaster | None = None,
           gbuffer: GBuffer | None = None, erode_px: int = 1, elm: str = "dhr",
           skins: tissue.SkinParams | Sequence[str | dict] | None = None,
           cache: MaterialCache | None = None, panel_pixels: list[list[torch.Tensor]] | None = None,
           compile: bool = False, sky_view: str = "field") -> RenderResult:
    """Render every sun x camera of ``scene`` and calibrate with ELM.

    Args:
        scene: the scene (``render.scene``).
        sensor: the sensor chain; ``None`` is an ideal linear sensor (ELM then recovers Lambertian reflectance
            exactly).
        box: the rules detector's thresholds.
        raycaster, gbuffer: reuse geometry across calls (a G-buffer without shadow masks gets them from
            ``raycaster``).
        erode_px: pixels eroded off each reference panel's edge before its median enters ELM.
        elm: "dhr" (the panels' hemispherical reflectance) or "brdf" (BRDF-ELM: their BRDF at the geometry).
        skins: a batch of skins (``tissue.SkinParams``, or presets / parameter dicts) for the material named
            "skin", every one under every sun in one pass: the leading axis is then skin-major (K x S).
        cache: where compiled material tables are kept across frames (``materials.MaterialCache``; default
            ``materials.SHARED_CACHE``, keyed on everything the tables depend on, ``data.tables_version()``
            included).
        panel_pixels: the reference panels' interior pixels in ``gbuffer`` (``elm.panel_pixels``), to skip
            finding them again when one G-buffer is rendered many times.
        compile: run the per-pixel stages (G-buffer assembly, shading, sensor, ELM) as fused compiled kernels
            (``render.kernels``; the first call compiles, for seconds); False: the same functions eagerly.
        sky_view: how each pixel's view of the sky and lit ground is found (outdoor light only): "field"
            (default) interpolates the geometry's ``visibility.VisibilityField``, cast once per ``raycaster`` and
            reused by every later frame of the same meshes; "rays" casts ``raycast.SKY_RAYS`` rays per pixel
            (cheaper for a single small frame or a few pixels; a noisier estimate).

    Returns:
        ``RenderResult``; images (S, C, H, W, B).

    >>> from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun
    >>> mats = {"grey": Material(reflectance=0.4), "white": Material(reflectance=0.97),
    ...         "dark": Material(reflectance=0.03)}
    >>> meshes = [MeshSpec("wall", "plane", "grey", {"width": 6, "height": 6}, position=[-1, 0, -2]),
    ...           MeshSpec("panel_white", "plane", "white", {"width": 0.4, "height": 0.4}, position=[0, 0.5, 0.8]),
    ...           MeshSpec("panel_dark", "plane", "dark", {"width": 0.4, "height": 0.4}, position=[0, -0.5, 0.8])]
    >>> cam = Camera(width=32, height=32, fov_deg=20.0)
    >>> res = render(Scene(mats, meshes, [cam], [Sun(zenith_deg=40.0)], illumination="thesis"))
    >>> res.reflectance.shape
    torch.Size([1, 1, 32, 32, 4])
    >>> [round(float(x), 4) for x in res.reflectance[0, 0, 2, 2]]  # ideal sensor, sun alone: ELM recovers the 0.4
    [0.4, 0.4, 0.4, 0.4]
    """
    timing: dict = {}
    t0 = time.perf_counter()
    check_sky_view(sky_view)
    check_materials(scene.materials, scene.band_list)  # before any mesh is built
    check_light(scene.illumination, scene.suns)
    light = scene_light(scene, dtype, device)
    gb, raycaster = geometry(scene, raycaster, gbuffer, timing, compile)
    t1 = time.perf_counter()
    pix = find_panel_pixels(gb, list(scene.panels), erode_px) if panel_pixels is None else panel_pixels
    hw = gb.hit[0].numel()  # the panels share one sky view each (flat indices over every camera's pixels)
    shared = [ix.cpu() + c * hw for per_cam in pix for c, ix in enumerate(per_cam)]
    field = raycaster.field_seconds if raycaster is not None else 0.0
    gb = cast_shadows(scene, gb, raycaster, light, shared, sky_view).to(device=torch.device(device), dtype=dtype)
    timing["sky_view_s"] = time.perf_counter() - t1
    if raycaster is not None and raycaster.field_seconds > field:  # the field's samples cast in this call
        timing["visibility_field_s"] = raycaster.field_seconds - field
    pix = [[ix.to(gb.hit.device) for ix in per_cam] for per_cam in pix]
    return render_gbuffer(scene, gb, pix, torch.device(device), dtype, sensor, box, elm, skins, cache, timing, t0,
                          compile, light)


def render_pixels(scene: Scene, pixels: torch.Tensor, device: torch.device | str = "cpu",
                  dtype: torch.dtype = torch.float32, sensor: Sensor | None = None, box: RulesBox = DEFAULT_BOX,
                  raycaster: Raycaster | None = None, gbuffer: GBuffer | None = None, erode_px: int = 1,
                  elm: str = "dhr", skins: tissue.SkinParams | Sequence[str | dict] | None = None,
                  cache: MaterialCache | None = None,
                  panel_pixels: list[list[torch.Tensor]] | None = None, compile: bool = False,
                  irradiance: Sequence[int] | None = None, light: LightTables | None = None,
                  sky_view: str = "field") -> RenderResult:
    """``render`` of the pixels ``pixels`` (flat indices into the single camera's H*W) and the panels' interior
    only: images have shape (S, 1, 1, K[, B]) for the K requested pixels, and automatic exposure uses the
    brightest of them and the panels (the dataset generator's fast path). Shadow rays (and sky-view rays) are
    cast for these pixels only when the G-buffer comes without them. ``irradiance``: band indices: also the
    direct and diffuse irradiance of each pixel in those bands (``RenderResult.irradiance``). ``light``: the
    scene's light tables if already computed (``scene_light``; cast to ``dtype`` and ``device``). Other
    arguments as ``render``."""
    timing: dict = {}
    t0 = time.perf_counter()
    check_sky_view(sky_view)
    check_materials(scene.materials, scene.band_list)
    check_light(scene.illumination, scene.suns)
    light = scene_light(scene, dtype, device) if light is None else light.to(device, dtype)
    gb, raycaster = geometry(scene, raycaster, gbuffer, timing, compile, shadows=False)
    pix = find_panel_pixels(gb, list(scene.panels), erode_px) if panel_pixels is None else \
        [[ix.to(gb.hit.device) for ix in per_cam] for per_cam in panel_pixels]
    panel_flat = [per_cam[0] for per_cam in pix]
    pixels = pixels.to(gb.hit.device).long()
    sizes = [len(pixels)] + [len(x) for x in panel_flat]
    pad = -sum(sizes) % PIXEL_MULTIPLE  # copies of the first pixel, so that kernels run in full vector lanes
    gb = gather_pixels(gb, torch.cat([pixels, *panel_flat, pixels[:1].expand(pad if len(pixels) else 0)]))
    offs = np.cumsum(sizes)
    shared = [torch.arange(int(offs[k]), int(offs[k + 1])) for k in range(len(panel_flat))]
    gb = cast_shadows(scene, gb, raycaster, light, shared, sky_view).to(device=torch.device(device), dtype=dtype)
    pix = [[torch.arange(int(offs[k]), int(offs[k + 1]), device=gb.hit.device)] for k in range(len(panel_flat))]
    res = render_gbuffer(scene, gb, pix, torch.device(device), dtype, sensor, box, elm, skins, cache, timing, t0,
                         compile, light, irradiance)
    n = len(pixels)
    if res.irradiance is not None:
        res.irradiance = (res.irradiance[0][..., :n, :], res.irradiance[1][..., :n, :])
    for name in ("radiance", "signal", "reflectance", "ndgri", "ndsi", "mask", "skin", "lit"):
        setattr(res, name, getattr(res, name)[..., :n, :] if getattr(res, name).dim() == 5 else getattr(res, name)[..., :n])
    return res


def render_gbuffer(scene: Scene, gb: GBuffer, pix: list[list[torch.Tensor]], device: torch.device,
                   dtype: torch.dtype, sensor: Sensor | None, box: RulesBox, elm: str,
                   skins: tissue.SkinParams | Sequence[str | dict] | None, cache: MaterialCache | None,
                   timing: dict, t0: float, compile: bool = False, light: LightTables | None = None,
                   irradiance: Sequence[int] | None = None) -> RenderResult:
    """The stages after the ray cast, on a G-buffer already on ``device`` (with its sky view when the light
    needs one): materials, shading, sensor, ELM with the panels' interior pixels ``pix``, the rules. ``light``:
    the scene's light tables (default: computed now). Arguments as ``render``."""
    batch = None if skins is None else skin_batch(skins)
    reps = 1 if batch is None else batch.shape[0]
    t2 = time.perf_counter()
    tables = material_tables(scene, gb, dtype, device, batch, cache)
    light = (scene_light(scene, dtype, device) if light is None else light).repeat(reps)
    shadow = gb.shadow_masks()
    if reps > 1:
        gb = GBuffer(**{**{f.name: getattr(gb, f.name) for f in fields(gb)},
                        "shadow": shadow.repeat(reps, *([1] * (shadow.dim() - 1)))})
    sun_dirs = torch.tensor(np.stack([s.direction for s in scene.suns]), dtype=dtype, device=device).repeat(reps, 1)
    sh = shade(gb, tables, light, sun_dirs, sky_background=scene.background == "sky", compile=compile)
    sync(device)
    timing["shade_s"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    gen = None
    if sensor is not None and sensor.noise:
        gen = torch.Generator(device=device)
        gen.manual_seed(int(sensor.seed))
    signal = sensor_signal(sh.radiance, sensor, scene.band_list, scene.cameras[0].focal, gen, compile=compile)
    if scene.panels:
        pv = panel_values(signal, pix)  # (S, C, P, B)
        panel_ids = [gb.material_names.index(scene.mesh(p).material) for p in scene.panels]
        refs = panel_references(panel_ids, gb, tables, sun_dirs, pix, elm)  # (S, C, P, B)
        refl, g, s, mask = calibrate_detect(signal, pv, refs, gb.hit, scene.band_list, box, compile)
    else:  # no reference panels: no ELM, so no reflectance and no detections (the radiance and signal stand)
        pv = refs = signal.new_zeros(*signal.shape[:2], 0, signal.shape[-1])
        refl = torch.full_like(signal, math.nan)
        g = s = torch.full(signal.shape[:-1], math.nan, dtype=signal.dtype, device=signal.device)
        mask = torch.zeros_like(gb.hit).expand(signal.shape[:-1])
    skin = gb.hit & tables.is_skin[gb.material.clamp_min(0)]
    sync(device)
    timing["sensor_elm_s"] = time.perf_counter() - t3
    timing["total_s"] = time.perf_counter() - t0
    panels = {p: {"reference": refs[:, :, k].tolist(), "signal": pv[:, :, k].tolist()}
              for k, p in enumerate(scene.panels)}
    irr = None
    if irradiance is not None:
        irr = tuple(x.reshape(*sh.radiance.shape[:-1], -1)
                    for x in shade_irradiance(gb, tables, light, sun_dirs, sh.lit, list(irradiance)))
    return RenderResult(sh.radiance, light, signal, refl, g, s, mask, skin, sh.lit, panels, gb, timing, scene.band_list,
                        pix, cast(tuple[torch.Tensor, torch.Tensor] | None, irr))


def calibrate_detect(signal: torch.Tensor, panel_signal: torch.Tensor, references: torch.Tensor, hit: torch.Tensor,
                     bands: tuple[Band, ...], box: RulesBox, compile: bool = False
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """ELM reflectance of a signal cube (S, C, H, W, B) from its panels' signals and references (S, C, P, B),
    then NDGRI, NDSI and the rules detector's mask on hit pixels (``kernels.elm_indices``, compiled with
    ``compile``); without the four index bands (544, 633, 1080, 1580 nm) NaN indices and an empty mask."""
    if has_index_bands(bands):
        a, b = elm_coefficients(panel_signal[:, :, 0], panel_signal[:, :, 1], references[:, :, 0],
                                references[:, :, 1])
        x, a, k = band_tiles(signal, a)
        b = b.reshape(a.shape[0], 1, -1).repeat(1, 1, k)
        refl, g, s, rules = KERNELS.get(elm_indices, compile, signal.device)(
            x, a, b, len(bands), index_band_positions(bands), box)
        shape = signal.shape[:-1]
        return refl.view(signal.shape), g.view(shape), s.view(shape), rules.view(shape) & hit
    refl = apply_elm(signal, panel_signal, references)
    g = s = torch.full(refl.shape[:-1], math.nan, dtype=refl.dtype, device=refl.device)
    return refl, g, s, torch.zeros_like(hit).expand(refl.shape[:-1])
