"""The full reflectance frames of ``generate --images``: a group's cubes made with its rows' draw (``frame_cubes``)
and a shard's cubes written as ``images/images-NNNNN.npy`` (``write_images``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .. import tissue
from ..detect import DEFAULT_BOX
from ..io import save_npy
from ..render.pipeline import PIXEL_MULTIPLE, RenderResult, calibrate_detect, render
from ..render.raycast import GBuffer, Raycaster
from ..render.scene import Scene
from ..render.sensor import Sensor, sensor_signal
from .files import IMAGES_DIR, sha256_file


def frame_cubes(scene: Scene, gb: GBuffer, rc: Raycaster, sensor: Sensor, skins: tissue.SkinParams,
                pix: list[list[torch.Tensor]], picks: np.ndarray, res: RenderResult, device: torch.device | str = "cpu",
                compile: bool = False) -> np.ndarray:
    """The full reflectance frames of a group's configurations, (skins·suns, bands, H, W) float16, made with the
    draw of its rows (``res``: ``render_pixels`` of the flat pixels ``picks`` and the panels' sample ``pix``): the
    same automatic exposure (the brightest of those pixels, per configuration and band), the same sensor noise at
    those pixels (fresh draws from the same stream elsewhere) and the same empirical line (``res``'s panel
    medians). So a row is its cube's pixel: its reflectance columns are the cube's value there (float16-rounded),
    and the rows are the bytes they are without ``--images``. The frames' radiance is ``render``'s (a pixel's
    shading and sky view do not depend on which other pixels are rendered)."""
    full = render(scene, device=device, sensor=None, gbuffer=gb, raycaster=rc, skins=skins, panel_pixels=pix,
                  compile=compile, sky_view="rays")  # the rows' sky view (generate.SKY_VIEW)
    rad = full.radiance  # (S·K, 1, H, W, B)
    n_cfg, n_bands = rad.shape[0], rad.shape[-1]
    flat = rad.view(n_cfg, 1, -1, n_bands)
    # the pixels render_pixels rendered, in its order (before its padding to PIXEL_MULTIPLE: copies of the first)
    drawn = torch.cat([torch.from_numpy(picks).long(), *[per_cam[0].cpu().long() for per_cam in pix]]).to(rad.device)
    reference = flat.index_select(2, drawn).amax(2)  # render_pixels' exposure: its brightest pixel, (S·K, 1, B)
    noise = None
    if sensor.noise:  # render_pixels' draws (render_gbuffer: a generator seeded with the sensor's seed), then more
        gen = torch.Generator(device=rad.device)
        gen.manual_seed(int(sensor.seed))
        rendered = len(drawn) + (-len(drawn) % PIXEL_MULTIPLE)
        rows_z = torch.randn((n_cfg, 1, 1, rendered, n_bands), generator=gen, dtype=rad.dtype, device=rad.device)
        noise = torch.randn(rad.shape, generator=gen, dtype=rad.dtype, device=rad.device)
        noise.view(n_cfg, 1, -1, n_bands)[:, :, drawn] = rows_z[:, :, 0, :len(drawn)]
    signal = sensor_signal(rad, sensor, scene.band_list, scene.cameras[0].focal, reference=reference,
                           compile=compile, noise=noise)
    panels = [[res.panels[p][k] for p in res.panels] for k in ("signal", "reference")]  # (P, S·K, C, B) each
    pv, refs = (torch.tensor(x, dtype=signal.dtype, device=signal.device).permute(1, 2, 0, 3).contiguous()
                for x in panels)
    refl = calibrate_detect(signal, pv, refs, full.gbuffer.hit, scene.band_list, DEFAULT_BOX, compile)[0]
    return refl[:, 0].permute(0, 3, 1, 2).cpu().numpy().astype(np.float16)


def write_images(out_dir: Path, k: int, cubes: list) -> dict:
    """Write a shard's image cubes, (groups, skins, suns, bands, H, W) float16, as ``images/images-NNNNN.npy``
    (a subfolder, so that Parquet readers of the dataset folder see only shards)."""
    arr = np.stack(cubes)
    (out_dir / IMAGES_DIR).mkdir(exist_ok=True)
    path = out_dir / IMAGES_DIR / f"images-{k:05d}.npy"
    save_npy(path, arr, suffix=".tmp")
    return {"name": f"{IMAGES_DIR}/{path.name}", "shape": list(arr.shape), "sha256": sha256_file(path),
            "bytes": path.stat().st_size}
