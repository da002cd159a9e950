"""Where a frame's time goes: open3d's bare ray casts against our wrappers, then every stage of ``render`` (the
4-band default scene, one sun; medians of repeated runs). A diagnostic for the renderer's speed work; compare
figures measured in one run, not across runs (this machine drifts by +-25 %).

    .venv/bin/python scripts/frame_costs.py [--size 512] [--repeat 7]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from torchskin.render.elm import apply_elm, panel_pixels, panel_references, panel_values
from torchskin.render.materials import MaterialCache
from torchskin.render.pipeline import render
from torchskin.render.raycast import Raycaster, rasterize
from torchskin.render.scene import Camera, Sun, default_scene
from torchskin.render.sensor import Sensor, sensor_signal
from torchskin.render.shade import shade


def median_ms(fn: Callable[[], object], repeat: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="frame width and height, pixels (default 512)")
    ap.add_argument("--repeat", type=int, default=7, help="timed runs per figure (default 7)")
    args = ap.parse_args()
    n = args.repeat
    sc = default_scene(camera=Camera(width=args.size, height=args.size),
                       sun=Sun(zenith_deg=40.0, azimuth_deg=25.0, sky_fraction=0.1))
    rc = Raycaster.from_scene(sc)
    sun_dirs = np.stack([s.direction for s in sc.suns])
    rays = rc.camera_rays(sc.cameras[0])[None]
    gb = rasterize(sc, rc)
    origins = gb.position.reshape(-1, 3)[gb.hit.flatten()]
    shadow_rays = torch.cat([origins, torch.as_tensor(sun_dirs, dtype=torch.float32).expand(len(origins), 3)], -1)
    o3d_rays, o3d_shadow = (rc.o3d.core.Tensor.from_numpy(np.ascontiguousarray(r.numpy())) for r in (rays, shadow_rays))
    out = {"bare_cast_rays": median_ms(lambda: rc.scene.cast_rays(o3d_rays), n),
           "bare_test_occlusions": median_ms(lambda: rc.scene.test_occlusions(o3d_shadow), n),
           "wrapped_cast": median_ms(lambda: rc.cast(rays), n),
           "wrapped_occluded": median_ms(lambda: rc.occluded(shadow_rays), n),
           "gbuffer_with_casts": median_ms(lambda: rc.gbuffer(sc.cameras, sun_dirs), n)}
    cache, sensor = MaterialCache(), Sensor()
    out["frame"] = median_ms(lambda: render(sc, sensor=sensor, gbuffer=rasterize(sc, rc), cache=cache), n)
    tables = cache.compile(sc.materials, sc.bands, sc.suns, gb.material_names)
    dirs = torch.tensor(sun_dirs, dtype=torch.float32)
    sky = torch.tensor([s.sky_fraction for s in sc.suns])
    out["panel_pixels"] = median_ms(lambda: panel_pixels(gb, list(sc.panels)), n)
    out["shade"] = median_ms(lambda: shade(gb, tables, dirs, sky), n)
    radiance = shade(gb, tables, dirs, sky).radiance
    out["sensor_without_noise"] = median_ms(
        lambda: sensor_signal(radiance, Sensor(noise=False), sc.band_list, sc.cameras[0].focal), n)
    gen = torch.Generator().manual_seed(0)
    out["noise_draw"] = median_ms(lambda: torch.randn(radiance.shape, generator=gen), n)
    signal = sensor_signal(radiance, sensor, sc.band_list, sc.cameras[0].focal, gen)
    pix = panel_pixels(gb, list(sc.panels))
    ids = [gb.material_names.index(sc.mesh(p).material) for p in sc.panels]
    out["elm"] = median_ms(lambda: apply_elm(signal, panel_values(signal, pix),
                                             panel_references(ids, gb, tables, dirs, pix)), n)
    r = out["bare_cast_rays"] + out["bare_test_occlusions"]
    print(json.dumps({**{f"{k}_ms": round(v, 2) for k, v in out.items()}, "frame_over_bare_casts": round(out["frame"] / r, 2)}))


if __name__ == "__main__":
    main()
