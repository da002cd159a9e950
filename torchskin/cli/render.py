"""``torchskin render``: ray-cast a subject between two reference panels under a sun, through the sensor chain;
calibrate with ELM and run the rules detector."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import torch

from .. import tissue
from ..bands import DEFAULT_BANDS, parse_bands, scene_bands
from ..errors import check_input_file, check_output_folder
from ..render.scene import Scene
from .options import (
    add_atmosphere,
    add_bands,
    add_device,
    add_frame,
    add_illumination,
    add_json,
    add_no_noise,
    add_out_folder,
    add_overwrite,
    add_panels,
    add_seed,
    add_sky,
    add_surface,
    atmosphere_from_args,
    check_angle,
    check_atmosphere,
    check_frame,
    check_number,
)


def _scene_from_args(args: argparse.Namespace) -> Scene:
    from ..render.scene import Camera, Sun, default_scene

    cam = Camera(width=args.width, height=args.height, zenith_deg=args.camera_zenith,
                 azimuth_deg=args.camera_azimuth, range_m=args.range, fov_deg=args.fov)
    atm = atmosphere_from_args(args)
    sun = Sun(zenith_deg=args.source_zenith, azimuth_deg=args.source_azimuth, sky_fraction=args.sky, atmosphere=atm)
    subject = "file" if args.mesh else "anny"
    sc = default_scene(subject=subject, mesh_path=args.mesh, skin=args.skin, camera=cam, sun=sun,
                       panels=args.panels, diffuse_only=args.diffuse_only, ground=not args.no_ground,
                       surface=args.surface, illumination=args.illumination)
    if args.bands:
        sc.bands = scene_bands(parse_bands(args.bands))
    if args.sky_background:
        sc.background = "sky"
    return sc


def cmd_render(args: argparse.Namespace) -> int:
    """Run ``torchskin render``: every option checked before any work, then one frame rendered, calibrated
    and written to ``--out`` (``render.outputs.write_outputs``)."""
    from ..devices import check_device
    from ..render.outputs import elm_warning, previous_outputs, write_outputs
    from ..render.pipeline import render
    from ..render.sensor import Sensor

    check_output_folder(args.out, "--out", overwrite=args.overwrite)
    check_angle("--source-zenith", args.source_zenith, 0, 90)
    check_angle("--camera-zenith", args.camera_zenith, 0, 180)
    check_number("--source-azimuth", args.source_azimuth, -360, 360)
    check_number("--camera-azimuth", args.camera_azimuth, -360, 360)
    check_number("--sky", args.sky, 0, 1)
    check_atmosphere(args)
    check_number("--range", args.range, 0.1, 1e5, "a distance in m")
    check_number("--fov", args.fov, 0.01, 179, "an angle in degrees")
    if args.mesh:
        check_input_file(args.mesh, "--mesh", (".obj", ".ply"))
    check_frame(args, len(parse_bands(args.bands)) if args.bands else len(DEFAULT_BANDS))
    if args.format == "tiff":  # the writer's package, before any work
        from ..cubefiles import _need

        _need("tifffile", "render --format tiff")
    device = check_device(args.device)
    sc = _scene_from_args(args)
    path: dict[str, Any] = {}
    if args.illumination == "spectrl2":  # the sensor's path through the light model's atmosphere
        from ..render.light import path_terms
        from ..render.pipeline import scene_light

        path = path_terms(sc.suns[0].atmosphere, scene_light(sc, torch.float64).sky[0].tolist(), sc.bands, args.range)
    sensor = Sensor(noise=not args.no_noise, seed=args.seed, **path)
    res = render(sc, device=device, sensor=sensor, elm=args.elm, compile=args.compile, sky_view=args.sky_view)
    for old in previous_outputs(args.out) if args.overwrite else []:  # the folder then holds this render only
        old.unlink()
    info = write_outputs(res, sc.to_dict(), args.out, sensor=sensor, fmt=args.format, sky_view=args.sky_view)
    warning = elm_warning(info)
    if warning:
        print(f"torchskin render: warning: {warning}", file=sys.stderr)
    if args.json:
        print(json.dumps({"timing_s": res.timing, "skin_pixels": info["skin_pixels"],
                          "detected_fraction": info["detected_fraction"], "panels": res.panels,
                          "sunlit_skin_pixels": info["sunlit_skin_pixels"],
                          "detected_fraction_sunlit": info["detected_fraction_sunlit"],
                          "elm_valid": info["elm_valid"], "panel_sunlit_fraction": info["panel_sunlit_fraction"],
                          "illumination": res.light.summary(res.bands)}))
    elif not info["rules_detector"]:
        print(f"skin pixels {info['skin_pixels']} (sunlit {info['sunlit_skin_pixels']}); no rules detector (the "
              f"bands lack 544, 633, 1080 or 1580 nm); {res.timing['total_s']:.2f} s; wrote {args.out}")
    else:
        print(f"skin pixels {info['skin_pixels']} (sunlit {info['sunlit_skin_pixels']}), inside the rules box "
              f"{info['detected_fraction']:.3f} (sunlit {info['detected_fraction_sunlit']:.3f}); "
              f"{res.timing['total_s']:.2f} s; wrote {args.out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin render`` command."""
    rp = sub.add_parser("render", help="render a calibrated multispectral frame of a subject with panels",
                        description="Ray-cast a subject between two reference panels under a sun, through the "
                                    "sensor chain, calibrate with ELM and run the rules detector.")
    add_out_folder(rp, "the frame's cubes, masks, figures and render.json")
    add_overwrite(rp, "an earlier render's files (those its render.json lists; other files are kept)")
    src = rp.add_mutually_exclusive_group()
    src.add_argument("--mesh", metavar="PATH", help="OBJ/PLY subject (all skin)")
    src.add_argument("--subject", choices=["anny"], default="anny", help="parametric anny body (default)")
    rp.add_argument("--skin", default="I-II", help=f"skin preset ({', '.join(tissue.PRESETS)})")
    rp.add_argument("--source-zenith", type=float, default=45.0, help="sun zenith, degrees (default 45)")
    rp.add_argument("--source-azimuth", type=float, default=20.0, help="sun azimuth from +x, degrees (default 20)")
    add_illumination(rp)
    add_atmosphere(rp)
    add_sky(rp)
    rp.add_argument("--sky-background", action="store_true",
                    help="rays that hit nothing above the horizon see the isotropic sky (radiance E_sky / pi) "
                         "instead of a black void")
    rp.add_argument("--sky-view", choices=["field", "rays"], default="field",
                    help="each pixel's view of the sky and lit ground: field (default) interpolates sample points "
                         "cast once per geometry (128 rays each), rays casts 32 rays per pixel (slower for large "
                         "frames, noisier)")
    rp.add_argument("--camera-zenith", type=float, default=90.0, help="camera zenith, degrees (default 90)")
    rp.add_argument("--camera-azimuth", type=float, default=0.0, help="camera azimuth, degrees (default 0)")
    rp.add_argument("--range", type=float, default=9.449, help="camera range, m (default 9.449 = 31 ft)")
    rp.add_argument("--fov", type=float, default=14.0, help="horizontal field of view, degrees (default 14)")
    add_frame(rp)
    add_bands(rp)
    rp.add_argument("--format", choices=["npy", "envi", "tiff"], default="npy",
                    help="the reflectance and signal cubes' format: npy (default; reflectance.npy, signal.npy, "
                         "each with a wavelength sidecar .bands.json), envi (reflectance.hdr over reflectance.img, "
                         "signal.hdr over signal.img) or tiff (reflectance.tif, signal.tif; needs torchskin[formats]); "
                         "each with wavelengths, FWHM and units")
    add_panels(rp)
    rp.add_argument("--elm", choices=["dhr", "brdf"], default="dhr",
                    help="calibrate with the panels' DHR (ELM) or their BRDF at the geometry (BRDF-ELM)")
    add_no_noise(rp)
    rp.add_argument("--diffuse-only", action="store_true", help="skin as the diffuse model (no specular lobe)")
    add_surface(rp)
    rp.add_argument("--no-ground", action="store_true", help="no ground plane")
    add_device(rp)
    add_seed(rp, "the sensor noise")
    rp.add_argument("--compile", action="store_true",
                    help="run the per-pixel stages as compiled kernels (torch.compile: seconds to compile, for "
                         "repeated renders; the same frame within 1e-5)")
    add_json(rp)
    rp.set_defaults(func=cmd_render)
    return rp
