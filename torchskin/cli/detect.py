"""``torchskin detect``: the skin mask of a reflectance cube with the exported detector, numpy and onnxruntime
only (``torchskin.cli.main`` dispatches here without importing torch; the runtime is ``torchskin.onboard``)."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..errors import Parser, check_input_file, check_output_file
from ..io import npy_header, parse_band_list, read_bands_sidecar, sidecar_path
from ..onboard import SHIPPED_DETECTOR, OnboardDetector, apply_plan, band_plan, detect_file, plan_bands
from .cubes import load_cube, write_mask_png
from .options import add_bands, add_json, add_max_megapixels, add_out_file, add_tile_rows

PROG = "torchskin detect"
DESCRIPTION = "Skin mask of a reflectance cube with the exported detector (numpy + onnxruntime, no torch)."
HELP = "skin mask of a cube with detector.onnx (numpy + onnxruntime only)"

#: the ``torchskin detect`` option (without ``--``, ``_`` for ``-``) that gives each configuration feature
FLAG_FOR_FEATURE = {"sun_zenith_deg": "sun_zenith", "camera_zenith_deg": "camera_zenith",
                    "relative_azimuth_deg": "relative_azimuth", "range_m": "range", "diffuse_share": "diffuse_share"}
#: the physical range of a feature whose values cannot lie outside it (a share): others may leave the training
#: domain (the runtime flags that), these are refused
PHYSICAL_RANGE = {"diffuse_share": (0.0, 1.0)}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The ``torchskin detect`` options."""
    ap.add_argument("--model", default=None,
                    help="detector.onnx (default: the shipped detector, packaged with torchskin: "
                         "torchskin/data/detector.onnx, a copy of the repository's exports/detector.onnx)")
    ap.add_argument("--cube", required=True, help="reflectance cube: .npy (bands, H, W) or (B, bands, H, W), an ENVI "
                    ".hdr (with its data file) or a multi-band GeoTIFF .tif, with wavelengths; other bands than the "
                    "model's are synthesised from the cube's spectra")
    add_bands(ap, default="the cube's sidecar CUBE.bands.json, written by render and calibrate; without either, "
                          "the cube must hold the model's bands, 544,633,1080,1580, in that order")
    ap.add_argument("--sun-zenith", type=float, help="degrees")
    ap.add_argument("--camera-zenith", type=float, help="degrees")
    ap.add_argument("--relative-azimuth", type=float, help="degrees, |sun - camera azimuth| in [0, 180]")
    ap.add_argument("--range", type=float, help="metres (if the model uses it)")
    ap.add_argument("--diffuse-share", type=float,
                    help="the sky's share of the light on a horizontal surface at 544 nm, in [0, 1]: a shaded "
                         "horizontal panel's signal over a sunlit one's (if the model uses it: lut detectors)")
    add_out_file(ap, "the mask of the first frame: .png; .tif (a GeoTIFF; required for a georeferenced GeoTIFF "
                     "cube, whose transform and CRS it keeps); or .hdr (ENVI; required for an ENVI cube with 'map "
                     "info', which it keeps)", required=False)
    add_tile_rows(ap)
    ap.add_argument("--clip-negative", action="store_true",
                    help="set negative reflectance (noise on dark pixels) to 0 and report how many values were "
                         "clipped, instead of refusing the cube")
    ap.add_argument("--min-reflectance", type=float, default=None,
                    help="pixels whose mean reflectance over the bands is not above this are never skin (their "
                         "indices are noise); default: the floor the model was evaluated with (its metadata "
                         "min_reflectance; 0 for models without it)")
    add_max_megapixels(ap)
    add_json(ap)


def detect_parser() -> Parser:
    """The ``torchskin detect`` argument parser, on its own (the torch-free path)."""
    ap = Parser(prog=PROG, description=DESCRIPTION)
    add_arguments(ap)
    return ap


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin detect`` entry of the full parser (the same options as ``detect_parser``)."""
    ap: argparse.ArgumentParser = sub.add_parser("detect", help=HELP, description=DESCRIPTION)
    add_arguments(ap)
    ap.set_defaults(func=cmd_detect)
    return ap


def configuration_values(args: argparse.Namespace, features: list[str]) -> list[float]:
    """The value of each configuration feature the model takes, from its option (``FLAG_FOR_FEATURE``)."""
    values = []
    for f in features:
        flag = FLAG_FOR_FEATURE.get(f, f)
        v = getattr(args, flag, None)
        if v is None:
            raise ValueError(f"the model needs --{flag.replace('_', '-')} ({f})")
        if not np.isfinite(v):
            raise ValueError(f"--{flag.replace('_', '-')} must be a finite number, got {v}")
        lo, hi = PHYSICAL_RANGE.get(f, (-np.inf, np.inf))
        if not lo <= v <= hi:
            raise ValueError(f"--{flag.replace('_', '-')} must lie in [{lo:g}, {hi:g}] (a share, not per cent), got {v:g}")
        values.append(v)
    return values


def model_bands(cube: np.ndarray, args: argparse.Namespace,
                det: OnboardDetector) -> tuple[np.ndarray, list[float] | None]:
    """The (B, bands, H, W) ``cube`` with the model's bands in the model's order, frame by frame by the plan of a
    one-frame cube (``onboard.band_plan``: the bands used as they are, reordered, or synthesised from the
    spectra): the cube's own wavelengths come from ``--bands`` or the sidecar beside ``--cube``
    (``io.read_bands_sidecar``); a cube that has neither must hold the model's bands in its order. ``ValueError``
    naming the option when the cube does not match. Also returns the bands assumed (the model's) when the cube
    gives no wavelengths, else None."""
    cube_bands: list[float] | None
    if args.bands:
        cube_bands, where = parse_band_list(args.bands), "--bands"
    else:
        cube_bands, where = read_bands_sidecar(args.cube), f"the sidecar {str(sidecar_path(args.cube))!r}"
    if cube_bands is None or not det.bands_nm:  # nothing to match (a model without bands_nm metadata: as given)
        return cube, (list(det.bands_nm) if det.bands_nm else None)
    if len(cube_bands) != cube.shape[1]:
        raise ValueError(f"{where} gives {len(cube_bands)} bands, but --cube {args.cube!r} holds {cube.shape[1]} "
                         f"(shape {cube.shape[1:]} per frame)")
    try:
        plan = band_plan(cube_bands, None, plan_bands(det))
    except ValueError as e:
        raise ValueError(f"--cube {args.cube!r} ({where}): {e}") from None
    return np.stack([apply_plan(plan, frame) for frame in cube]), None


def cli_detect(argv: list[str]) -> int:
    """``torchskin detect [--model detector.onnx] --cube CUBE.npy --sun-zenith DEG --camera-zenith DEG
    --relative-azimuth DEG [--range M] [--out MASK.png] [--json]`` (numpy + onnxruntime only)."""
    return cmd_detect(detect_parser().parse_args(argv))


def cmd_detect(args: argparse.Namespace) -> int:
    """Run ``torchskin detect`` on parsed options: a one-frame cube streams in row tiles (``onboard.detect_file``),
    a (B, bands, H, W) ``.npy`` is read whole."""
    mask_path = check_output_file(args.out, "--out", (".png", ".tif", ".tiff", ".hdr")) if args.out else None
    det = OnboardDetector(check_input_file(SHIPPED_DETECTOR if args.model is None else args.model, "--model",
                                           (".onnx",)))
    negative = "clip" if args.clip_negative else "error"
    if not _batched_npy(args.cube):
        values = configuration_values(args, det.features)
        res = detect_file(det, args.cube, values, mask_path, args.tile_rows, negative, args.min_reflectance,
                          parse_band_list(args.bands) if args.bands else None, max_megapixels=args.max_megapixels)
        n, total = res["skin_pixels"], res["pixels"]
        ood = res["out_of_domain"]
        clipped_list = res.get("clipped_values")
        shape = [1, *res["shape"]]
        assumed = res.get("bands_assumed")
    else:
        if mask_path is not None and mask_path.suffix.lower() != ".png":
            raise ValueError(f"--out {args.out!r}: a .npy cube carries no georeferencing; give a .png mask")
        cube = load_cube(args.cube, "--cube", args.max_megapixels)
        cube, assumed = model_bands(cube, args, det)
        values = configuration_values(args, det.features)
        out = det(cube, np.tile(np.array(values, dtype=np.float64), (cube.shape[0], 1)),
                  negative=negative, min_reflectance=args.min_reflectance)
        if mask_path is not None:
            write_mask_png(mask_path, out["mask"][0])
        n, total = int(out["mask"].sum()), int(out["mask"].size)
        ood = out["out_of_domain"].tolist()
        clipped = out.get("clipped_values")
        clipped_list = None if clipped is None else clipped.tolist()
        shape = list(out["mask"].shape)
    frac = n / total
    warnings = [] if not assumed else [assumed_bands_warning(args.cube, assumed)]
    for w in warnings:
        print(f"{PROG}: warning: {w}", file=sys.stderr)
    if args.json:
        doc = {"skin_fraction": frac, "skin_pixels": n, "out_of_domain": ood, "shape": shape}
        if warnings:
            doc["warnings"] = warnings
        if clipped_list is not None:
            doc["clipped_values"] = clipped_list
        print(json.dumps(doc))
    else:
        flag = " (configuration OUTSIDE the training domain)" if any(ood) else ""
        clip = f"; {sum(clipped_list)} negative values clipped to 0" if clipped_list is not None else ""
        print(f"skin pixels {n} of {total} ({frac:.4f}){flag}{clip}")
    return 0


def assumed_bands_warning(cube: str, bands: list[float]) -> str:
    """The warning for a cube read without wavelengths (a ``.npy`` without its sidecar, no ``--bands``): its bands
    were taken as the model's, in the model's order, which a cube in another order silently breaks."""
    return (f"--cube {str(cube)!r} gives no wavelengths (no sidecar {str(sidecar_path(cube))!r}, no --bands): its "
            f"{len(bands)} bands were read as the model's {', '.join(f'{b:g}' for b in bands)} nm, in that order")


def _batched_npy(path: str) -> bool:
    """Whether ``--cube`` is a ``.npy`` of several frames (B, bands, H, W) (read whole, as before streaming)."""
    if not str(path).lower().endswith(".npy"):
        return False
    try:
        return len(npy_header(path)[0]) != 3
    except (OSError, ValueError, EOFError, SyntaxError):
        return True  # load_cube gives the one-line error
