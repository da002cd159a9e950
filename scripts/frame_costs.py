"""Where a frame's time goes: open3d's bare ray casts against our wrappers, then every stage of ``render`` (the
4-band default scene, one sun; medians of repeated runs), eager and with the compiled kernels
(``render.kernels``), side by side. A diagnostic for the renderer's speed work; compare figures measured in one
run, not across runs (this machine drifts by +-25 %).

    .venv/bin/python scripts/frame_costs.py [--size 512] [--repeat 7] [--paths eager,compiled] [--plot PNG]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from torchskin.detect import DEFAULT_BOX
from torchskin.render.elm import panel_pixels, panel_references, panel_values
from torchskin.render.kernels import compiler_available
from torchskin.render.materials import MaterialCache
from torchskin.render.pipeline import calibrate_detect, render, scene_light
from torchskin.render.raycast import Raycaster
from torchskin.render.scene import Camera, Scene, Sun, default_scene
from torchskin.render.sensor import Sensor, sensor_signal
from torchskin.render.shade import shade

#: stacked-bar segments of the plot: label -> how it is computed from the measured figures
SEGMENTS = {"cast_rays (open3d)": lambda o: o["bare_cast_rays"],
            "test_occlusions (open3d)": lambda o: o["bare_test_occlusions"],
            "G-buffer, shadow-ray set-up": lambda o: o["gbuffer_with_casts"] - o["bare_cast_rays"] - o["bare_test_occlusions"],
            "shading": lambda o: o["shade"], "sensor (no noise)": lambda o: o["sensor_without_noise"],
            "noise draw (eager)": lambda o: o["noise_draw"], "panel pixels": lambda o: o["panel_pixels"],
            "ELM, indices, rules": lambda o: o["elm_rules"]}


def median_ms(fn: Callable[[], object], repeat: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def costs(sc: Scene, rc: Raycaster, compiled: bool, n: int) -> dict[str, float]:
    """Median milliseconds of the bare casts, the wrapped casts, each stage and the whole frame."""
    sun_dirs = np.stack([s.direction for s in sc.suns])
    rays = rc.camera_rays(sc.cameras[0])[None]
    gb = rc.gbuffer(sc.cameras, sun_dirs)
    origins = gb.position.reshape(-1, 3)[gb.hit.flatten()]
    shadow_rays = torch.cat([origins, torch.as_tensor(sun_dirs, dtype=torch.float32).expand(len(origins), 3)], -1)
    o3d_rays, o3d_shadow = (rc.o3d.core.Tensor.from_numpy(np.ascontiguousarray(r.numpy())) for r in (rays, shadow_rays))
    out = {"bare_cast_rays": median_ms(lambda: rc.scene.cast_rays(o3d_rays), n),
           "bare_test_occlusions": median_ms(lambda: rc.scene.test_occlusions(o3d_shadow), n),
           "wrapped_cast": median_ms(lambda: rc.cast(rays), n),
           "wrapped_occluded": median_ms(lambda: rc.occluded(shadow_rays), n),
           "gbuffer_with_casts": median_ms(lambda: rc.gbuffer(sc.cameras, sun_dirs, compiled), n)}
    cache, sensor = MaterialCache(), Sensor()
    out["frame"] = median_ms(lambda: render(sc, sensor=sensor, raycaster=rc, cache=cache, compile=compiled), n)
    tables = cache.compile(sc.materials, sc.bands, sc.suns, gb.material_names, illumination=sc.illumination)
    dirs = torch.tensor(sun_dirs, dtype=torch.float32)
    light = scene_light(sc)
    if light.needs_sky_view:
        out["sky_view"] = median_ms(lambda: rc.with_sky_view(gb), n)
        gb = rc.with_sky_view(gb)
    out["panel_pixels"] = median_ms(lambda: panel_pixels(gb, list(sc.panels)), n)
    out["shade"] = median_ms(lambda: shade(gb, tables, light, dirs, compile=compiled), n)
    radiance = shade(gb, tables, light, dirs).radiance
    out["sensor_without_noise"] = median_ms(
        lambda: sensor_signal(radiance, Sensor(noise=False), sc.band_list, sc.cameras[0].focal, compile=compiled), n)
    gen = torch.Generator().manual_seed(0)
    out["noise_draw"] = median_ms(lambda: torch.randn(radiance.shape, generator=gen), n)
    signal = sensor_signal(radiance, sensor, sc.band_list, sc.cameras[0].focal, gen)
    pix = panel_pixels(gb, list(sc.panels))
    ids = [gb.material_names.index(sc.mesh(p).material) for p in sc.panels]

    def elm_rules():
        refs = panel_references(ids, gb, tables, dirs, pix)
        return calibrate_detect(signal, panel_values(signal, pix), refs, gb.hit, sc.band_list, DEFAULT_BOX, compiled)

    out["elm_rules"] = median_ms(elm_rules, n)
    return out


def plot(results: dict[str, dict[str, float]], path: str, size: int) -> None:
    from torchskin.plots import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9.0, 3.4))
    names = list(results)
    colours = plt.get_cmap("tab10").colors
    for i, name in enumerate(names):
        o, left = results[name], 0.0
        for k, (label, f) in enumerate(SEGMENTS.items()):
            w = max(f(o), 0.0)
            ax.barh(i, w, left=left, color=colours[k], label=label if i == 0 else None, edgecolor="white", lw=0.5)
            left += w
        ax.barh(i, max(o["frame"] - left, 0.0), left=left, color="0.85", label="other (Python, glue)" if i == 0 else None)
        r = o["bare_cast_rays"] + o["bare_test_occlusions"]
        ax.text(o["frame"] + 1.5, i, f"{o['frame']:.0f} ms\n= {o['frame'] / r:.1f} × casts", va="center", fontsize=9)
    r = min(o["bare_cast_rays"] + o["bare_test_occlusions"] for o in results.values())
    ax.axvline(1.5 * r, color="k", ls="--", lw=1)
    ax.text(1.5 * r + 0.8, -0.55, "1.5 × casts (target)", fontsize=8, va="bottom")
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(-0.6, len(names) - 0.4)
    ax.set_xlabel("milliseconds per frame (medians of repeated runs)")
    ax.set_xlim(0, max(o["frame"] for o in results.values()) * 1.22)
    ax.set_title(f"A 4-band {size} × {size} frame of the default scene, sensor noise on: where the time goes "
                 "(2-core CPU)", fontsize=10)
    ax.legend(fontsize=8, ncol=1, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=130)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="frame width and height, pixels (default 512)")
    ap.add_argument("--repeat", type=int, default=7, help="timed runs per figure (default 7)")
    ap.add_argument("--paths", default="eager,compiled", help="eager, compiled or both (default both)")
    ap.add_argument("--plot", metavar="PNG", help="also draw the stage costs of each path as stacked bars")
    args = ap.parse_args()
    paths = [p.strip() for p in args.paths.split(",") if p.strip()]
    if not paths or set(paths) - {"eager", "compiled"}:
        raise SystemExit(f"--paths takes eager and/or compiled, got {args.paths!r}")
    if "compiled" in paths and not compiler_available("cpu"):
        raise SystemExit("no C++ compiler: only --paths eager can run")
    sc = default_scene(camera=Camera(width=args.size, height=args.size),
                       sun=Sun(zenith_deg=40.0, azimuth_deg=25.0, sky_fraction=0.1))
    rc = Raycaster.from_scene(sc)
    results = {}
    for p in paths:
        out = results[p] = costs(sc, rc, p == "compiled", args.repeat)
        r = out["bare_cast_rays"] + out["bare_test_occlusions"]
        print(json.dumps({"path": p, **{f"{k}_ms": round(v, 2) for k, v in out.items()},
                          "frame_over_bare_casts": round(out["frame"] / r, 2)}))
    if args.plot:
        plot(results, args.plot, args.size)


if __name__ == "__main__":
    main()
