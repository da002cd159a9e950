"""Benchmark harness behind ``torchskin bench``: each entry returns a JSON-ready dict.

Figures are medians of repeated runs after a warm-up; compare ratios measured in one run, not absolute
times across machines.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import torch

from . import tissue
from .render.pipeline import sync


def _median_seconds(fn: Callable[[], object], device: torch.device, repeat: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    sync(device)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def km_throughput(
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    n_skins: int = 100_000,
    n_wavelengths: int = 64,
    repeat: int = 5,
    compile: bool = False,
) -> dict:
    """Skin x wavelength evaluations per second of the full model (nine layers, substrate, surface)."""
    device = torch.device(device)
    skins, _ = tissue.sample(n_skins, 0, dtype=dtype, device=device)
    wl = torch.linspace(400.0, 1690.0, n_wavelengths, dtype=dtype, device=device)

    def run():
        with torch.no_grad():
            return tissue.total_reflectance(skins, wl, compile=compile)

    sec = _median_seconds(run, device, repeat, warmup=2 if compile else 1)
    return {
        "samples_x_bands_per_s": n_skins * n_wavelengths / sec,
        "seconds": sec,
        "skins": n_skins,
        "wavelengths": n_wavelengths,
        "device": str(device),
        "dtype": str(dtype).replace("torch.", ""),
        "compiled": compile,
        "threads": torch.get_num_threads(),
    }


def bench_km(compile: bool = False) -> dict:
    out = {"km": km_throughput("cpu")}
    if compile:
        out["km_compiled"] = km_throughput("cpu", compile=True)
    if torch.cuda.is_available():
        out["km_cuda"] = km_throughput("cuda", n_skins=1_000_000)
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        out["km_mps"] = km_throughput("mps", n_skins=1_000_000)
    return out


def _compiled_available() -> bool:
    from .render.kernels import compiler_available

    return compiler_available("cpu")


def _first_and_steady(fn: Callable[[], object], device: torch.device, repeat: int) -> tuple[float, float]:
    """Wall time of the first call (compilation included) and the steady-state median."""
    t0 = time.perf_counter()
    fn()
    sync(device)
    first = time.perf_counter() - t0
    return first, _median_seconds(fn, device, repeat, warmup=1)


def bench_render(compile: bool = False, width: int = 512, height: int = 512, repeat: int = 5,
                 device: str = "cpu") -> dict:
    """A 4-band frame of an anny subject with panels, ground, sun and shadows, eager and with the compiled
    kernels (``render.kernels``; the first compiled frame's extra time is ``compile_seconds``), against open3d's
    own ``cast_rays`` + ``test_occlusions`` for the same rays; the sensor noise draw of one frame on its own; and
    16 sun directions shaded from one G-buffer.

    The frames share one camera and one ray caster, as a renderer's frames of a fixed camera do: the sky view's
    field is cast once (``visibility_field_seconds``, the first frame's extra) and the camera's pixels look it up
    once (``sky_view_new_camera_seconds``: a frame from a camera not seen before pays this again)."""
    import dataclasses

    import numpy as np

    from .render.kernels import KERNELS
    from .render.materials import MaterialCache
    from .render.pipeline import render
    from .render.raycast import Raycaster
    from .render.scene import Camera, Sun, default_scene
    from .render.sensor import Sensor

    sc = default_scene(camera=Camera(width=width, height=height), sun=Sun(zenith_deg=40.0, azimuth_deg=25.0,
                                                                          sky_fraction=0.1))
    rc = Raycaster.from_scene(sc)
    sensor = Sensor()
    sun_dirs = np.stack([s.direction for s in sc.suns])
    dev = torch.device(device)
    cache = MaterialCache()  # the same materials every frame: compiled once, as a renderer keeps its scene
    suns16 = [Sun(zenith_deg=20.0 + 4 * k, azimuth_deg=-80.0 + 10 * k, sky_fraction=0.1) for k in range(16)]
    sc16 = default_scene(camera=sc.cameras[0], sun=suns16[0])
    sc16.suns = suns16

    def frame(compiled: bool, scene=sc):
        return lambda: render(scene, device=dev, sensor=sensor, raycaster=rc, cache=cache, compile=compiled)

    rays = rc.camera_rays(sc.cameras[0])[None]
    gb0 = rc.gbuffer(sc.cameras, sun_dirs)
    hit = gb0.hit.flatten()
    org = gb0.position.reshape(-1, 3)[hit]
    srays = torch.cat([org, torch.as_tensor(sun_dirs, dtype=torch.float32).expand(len(org), 3)], -1)

    def raw():
        rc.cast(rays)
        rc.occluded(srays)

    gen = torch.Generator().manual_seed(0)
    shape = (1, 1, height, width, len(sc.bands))
    out: dict[str, Any] = {"raycast_seconds": _median_seconds(raw, torch.device("cpu"), repeat, warmup=2),
                           "noise_draw_seconds": _median_seconds(lambda: torch.randn(shape, generator=gen),
                                                                 torch.device("cpu"), repeat)}
    paths = [False] + ([True] if _compiled_available() else [])
    for compiled in paths:
        tag = "compiled" if compiled else "eager"
        if compiled:  # compiled afresh in this process (Inductor's disk cache may still serve its code)
            KERNELS.clear()
            torch._dynamo.reset()
            first, t = _first_and_steady(frame(True), dev, repeat)
            out["compile_seconds"] = max(first - t, 0.0)
        else:
            t = _median_seconds(frame(False), dev, repeat, warmup=2)
        out[f"seconds_{tag}"] = t
        out[f"ratio_to_raycast_{tag}"] = t / out["raycast_seconds"]
        out[f"multi_source_frames_per_s_{tag}"] = 16 / _median_seconds(frame(compiled, sc16), dev, max(2, repeat // 2))
    best = "compiled" if len(paths) == 2 else "eager"
    res = frame(best == "compiled")()
    # the sky view's one-time cost: the field's sample points, cast on a fresh ray caster of the same meshes; and
    # a new camera's lookup (its rays not the cached ones: every pixel interpolated again)
    t0 = time.perf_counter()
    fresh = Raycaster(rc.meshes, rc.material_names)
    fresh.visibility_field().lookup(gb0, hit.nonzero().flatten(), torch.zeros(hit.numel()),
                                    torch.zeros(hit.numel(), len(rc.material_names)))  # every sample cast
    out["visibility_field_seconds"] = time.perf_counter() - t0
    new_camera = dataclasses.replace(gb0, rays=gb0.rays.clone())
    out["sky_view_new_camera_seconds"] = _median_seconds(
        lambda: fresh.with_sky_view(new_camera, method="field"), torch.device("cpu"), repeat, warmup=1)
    return {"render": {
        "seconds": out[f"seconds_{best}"], "ratio_to_raycast": out[f"ratio_to_raycast_{best}"],
        "multi_source_frames_per_s": out[f"multi_source_frames_per_s_{best}"], "path": best, **out,
        "width": width, "height": height, "bands": len(sc.bands), "device": str(dev),
        "stages_s": {k: v for k, v in res.timing.items() if k != "build_s"},
    }}


def bench_fit(compile: bool = False, n: int = 10_000) -> dict:
    """``fit_skin`` on n noisy visible spectra (400-1000 nm every 10 nm), default settings."""
    from .fit import fit_skin

    wl = tissue.wavelength_grid(400.0, 1000.0, 10.0, dtype=torch.float64)
    skins, _ = tissue.sample(n, 5, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    R = (tissue.total_reflectance(skins, wl) + 0.005 * torch.randn(n, wl.numel(), generator=g,
                                                                    dtype=torch.float64)).clamp(0, 1)
    t0 = time.perf_counter()
    res = fit_skin(R, wl)
    sec = time.perf_counter() - t0
    return {"fit": {"spectra_per_s": n / sec, "seconds_for_10000": sec * 10_000 / n, "spectra": n,
                    "wavelengths": wl.numel(), "converged_fraction": float(res.converged.float().mean()),
                    "rmse_median": float(res.rmse.median())}}


def _band_slice(tables, b: int):
    """Material tables of band ``b`` only (for the per-band baseline)."""
    import dataclasses

    n_bands = tables.wavelengths.shape[0]

    def one(v):
        return v[..., b:b + 1] if v.shape[-1] == n_bands else v

    groups = {k: dataclasses.replace(g, params={p: one(v) for p, v in g.params.items()}) for k, g in tables.groups.items()}
    return dataclasses.replace(tables, lambert_f=one(tables.lambert_f), albedo=one(tables.albedo),
                               reference=one(tables.reference), wavelengths=one(tables.wavelengths), groups=groups)


def _graphs_compiled() -> int:
    """Graphs torch.compile has compiled in this process so far (first compilations and recompilations)."""
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"])


def bench_dataset(compile: bool = False, width: int = 256, height: int = 256, groups: int = 32, repeat: int = 3,
                  baseline_images: int = 24) -> dict:
    """Dataset generation through ``dataset.generate.generate``: ``groups`` pose groups of the default config
    (16 suns x 3 skins each, confuser counts, atmospheres and sensor settings varying from group to group),
    Parquet shards written, eager and with the compiled kernels alternated in one run (medians of ``repeat``),
    after a warm-up of one shard per path (anny's and the compiler's first calls). ``graphs_compiled_after_warmup``
    counts compilations during the timed runs: 0 when no group's shapes or settings recompile a kernel. Against
    rendering each (configuration, band) image on its own with its own ray cast, the way a per-band renderer must
    (timed on ``baseline_images`` images, scaled to the same configurations)."""
    import dataclasses
    import tempfile

    from .dataset.config import resolve_config, sample_group
    from .dataset.generate import generate, group_scene, group_sensor
    from .render.light import light_tables
    from .render.materials import compile_materials
    from .render.raycast import Raycaster
    from .render.scene import Material
    from .render.sensor import sensor_signal
    from .render.shade import shade

    cfg = resolve_config({"camera": {"width": width, "height": height}})
    per_group = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"]
    n_configs = groups * per_group
    paths = [False] + ([True] if _compiled_available() else [])
    timed: dict[bool, list[float]] = {p: [] for p in paths}
    compile_s = 0.0
    graphs = 0
    with tempfile.TemporaryDirectory() as tmp:
        for p in paths:  # warm-up: one shard (anny, material tables; the compiled kernels' compilation)
            t0 = time.perf_counter()
            generate(cfg, per_group * cfg["sampling"]["groups_per_shard"], 99, f"{tmp}/warm-{p}", quiet=True, compile=p)
            if p:
                compile_s = time.perf_counter() - t0
        for r in range(repeat):  # alternated, so that both paths see the same machine
            for p in paths:
                g0 = _graphs_compiled()
                t0 = time.perf_counter()
                man = generate(cfg, n_configs, 0, f"{tmp}/run-{r}-{p}", quiet=True, compile=p)
                timed[p].append(time.perf_counter() - t0)
                graphs += _graphs_compiled() - g0
        rows = sum(s["rows"] for s in man["shards"])
    t_eager = statistics.median(timed[False])
    t_batched = statistics.median(timed[paths[-1]])
    g = sample_group(cfg, 0, 0)
    suns, skins = cfg["sun"]["per_pose"], cfg["skin"]["per_pose"]
    sc = group_scene(g)
    rc = Raycaster.from_scene(sc)
    sensor = group_sensor(g)
    n_bands = len(sc.bands)
    work = [(s, k, b) for k in range(skins) for s in range(suns) for b in range(n_bands)]
    step = max(1, len(work) // baseline_images)
    sample = work[::step][:baseline_images]
    t0 = time.perf_counter()
    for s, k, b in sample:
        sc.materials["skin"] = Material("skin", skin={name: float(getattr(g.skins, name)[k]) for name in tissue.PARAM_NAMES})
        gb = rc.gbuffer(sc.cameras, sc.suns[s].direction[None])
        band = [sc.bands[b]]
        light = light_tables(sc.illumination, [sc.suns[s]], band, torch.float32)
        gb = rc.with_sky_view(gb) if light.needs_sky_view else gb  # a per-band renderer casts its sky rays too
        tables = _band_slice(compile_materials(sc.materials, sc.bands, sc.suns, gb.material_names,
                                               illumination=sc.illumination), b)
        sun = torch.tensor(sc.suns[s].direction[None], dtype=torch.float32)
        L = shade(gb, tables, light, sun).radiance
        one_band: dict[str, Any] = {f: [getattr(sensor, f)[b]] for f in (
            "quantum_efficiency", "atmosphere_transmittance", "path_radiance") if isinstance(getattr(sensor, f), list)}
        band_sensor = dataclasses.replace(sensor, **one_band)
        sensor_signal(L, band_sensor, [sc.band_list[b]], sc.cameras[0].focal)
    t_per_image = (time.perf_counter() - t0) / len(sample)
    t_baseline_per_config = t_per_image * len(work) / (suns * skins)
    return {"dataset": {
        "configs_per_s": n_configs / t_batched, "configs_per_s_eager": n_configs / t_eager,
        "compiled_over_eager": t_eager / t_batched, "path": "compiled" if paths[-1] else "eager",
        "first_compiled_seconds": compile_s, "graphs_compiled_after_warmup": graphs if len(paths) == 2 else None,
        "samples_per_s": rows / t_batched,
        "speedup_vs_per_config_render": t_baseline_per_config * n_configs / t_batched, "batched_seconds": t_batched,
        "per_image_seconds": t_per_image, "groups": groups, "configs": n_configs, "width": width, "height": height,
        "groups_per_shard": cfg["sampling"]["groups_per_shard"],
    }}


def bench_detector_onnx(compile: bool = False, repeat: int = 20) -> dict:
    """The shipped detector (``torchskin/data/detector.onnx``: the lookup table, run by the onboard numpy head, and
    its brightness floor, ``min_reflectance`` in its metadata) through ``torchskin.onboard`` on a 1024 x 1024 x 4
    float32 frame (uniform reflectance 0.02-0.62, seed 0; sun 40 degrees, camera 30, azimuth 60, diffuse share
    0.2; the share of it the detector takes is reported), a single box query (a default ``BoxModel`` from seed 0,
    exported), and the memory-bound floor: reading the same frame once (numpy sum), in the same run."""
    import tempfile

    import numpy as np

    from .detectors.boxes import BoxModel
    from .export import export
    from .onboard import OnboardBoxes, OnboardDetector

    with tempfile.TemporaryDirectory() as d:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            paths = export(BoxModel(), d)
        det, bnd = OnboardDetector(), OnboardBoxes(paths["boundaries"])
        rng = np.random.default_rng(0)
        cube = (rng.random((1, 4, 1024, 1024), dtype=np.float32) * 0.6 + 0.02).astype(np.float32)
        cfg = np.array([[40.0, 30.0, 60.0]])  # the box query's angles
        frame_cfg = [det.config_row(sun_zenith_deg=40.0, camera_zenith_deg=30.0, relative_azimuth_deg=60.0,
                                    diffuse_share=0.2)]
        cpu = torch.device("cpu")
        share = float(det(cube, frame_cfg)["mask"].mean())
        t_frame = _median_seconds(lambda: det(cube, frame_cfg), cpu, repeat, warmup=3)
        t_query = _median_seconds(lambda: bnd(cfg), cpu, repeat * 10, warmup=10)
        t_read = _median_seconds(lambda: float(cube.sum()), cpu, repeat, warmup=3)
    return {"detector_onnx": {"ms_per_1mp_frame": 1e3 * t_frame, "us_per_boundary_query": 1e6 * t_query,
                              "memory_read_ms_1mp": 1e3 * t_read, "share_taken": share,
                              "min_reflectance": det.default_min_reflectance}}


def bench_materials(compile: bool = False, skins: int = 16, repeat: int = 5) -> dict:
    """Compiling a scene's materials (``render.materials.compile_materials``) for ``skins`` skins: once per skin
    (each its own scene) against once for the whole ``SkinParams`` batch, in the same run."""
    from .render.materials import compile_materials
    from .render.scene import Material, default_scene

    sc = default_scene(subject="file", mesh_path="unused.obj")  # materials only: the mesh is never built
    batch, _ = tissue.sample(skins, 0, dtype=torch.float64)
    values = batch.as_dict()
    per_skin = [{**sc.materials, "skin": Material("skin", skin={k: v[i] for k, v in values.items()})}
                for i in range(skins)]
    cpu = torch.device("cpu")
    t_one = _median_seconds(lambda: [compile_materials(m, sc.bands, sc.suns) for m in per_skin], cpu, repeat)
    t_batch = _median_seconds(lambda: compile_materials(sc.materials, sc.bands, sc.suns, skins=batch), cpu, repeat)
    return {"materials": {"skins": skins, "one_by_one_ms": 1e3 * t_one, "batched_ms": 1e3 * t_batch,
                          "speedup": t_one / t_batch}}


#: name -> ``callable(**options)`` returning a dict of results (later issues add entries)
BENCHMARKS: dict[str, Callable[..., dict]] = {"km": bench_km, "render": bench_render, "fit": bench_fit,
                                               "dataset": bench_dataset, "detector_onnx": bench_detector_onnx,
                                               "materials": bench_materials}


def run(only: list[str] | None = None, compile: bool = False) -> dict:
    names = list(BENCHMARKS) if not only else only
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        raise ValueError(f"unknown benchmark(s) {unknown}; available: {', '.join(BENCHMARKS)}")
    results: dict = {}
    for n in names:
        results.update(BENCHMARKS[n](compile=compile))
    return results
