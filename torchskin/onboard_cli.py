"""The onboard command line, numpy (and onnxruntime) only: ``torchskin calibrate`` (ELM: signals to reflectance
through reference panels in the frame) and ``torchskin detect`` (the exported detector on a reflectance cube),
with their argument parsing, ``.npy`` reading and mask PNG writing. ``torchskin.cli`` dispatches here without
importing torch; the runtime itself (model loading, ELM, detection) is ``torchskin.onboard``."""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from .errors import Parser, check_input_file, check_output_file, one_line
from .io import MAX_MEGAPIXELS, save_npy, write_png, write_text
from .onboard import OnboardDetector, elm_apply, elm_fit, load_cube

#: the ``torchskin detect`` option (without ``--``, ``_`` for ``-``) that gives each configuration feature
FLAG_FOR_FEATURE = {"sun_zenith_deg": "sun_zenith", "camera_zenith_deg": "camera_zenith",
                    "relative_azimuth_deg": "relative_azimuth", "range_m": "range"}


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """``"Y0:Y1:X0:X1"`` (rows Y0..Y1-1, columns X0..X1-1) -> a tuple of ints.

    >>> parse_roi("4:20:40:56")
    (4, 20, 40, 56)
    """
    parts = str(text).split(":")
    try:
        roi = tuple(int(p) for p in parts)
    except ValueError:
        roi = ()
    if len(roi) != 4:
        raise ValueError(f"a panel region must be Y0:Y1:X0:X1 (integers), got {text!r}")
    return roi  # type: ignore[return-value]  # four ints, checked above


def parse_panel(text: str) -> tuple[tuple[int, int, int, int], float | list[float]]:
    """A ``--panel`` value ``"Y0:Y1:X0:X1=REFL[,REFL...]"`` -> (region, reflectance: one value or one per band).

    >>> parse_panel("4:20:4:20=0.97"), parse_panel("1:3:1:3=0.4,0.5")
    (((4, 20, 4, 20), 0.97), ((1, 3, 1, 3), [0.4, 0.5]))
    """
    roi, sep, rho = text.partition("=")
    try:
        vals = [float(v) for v in rho.split(",")] if sep else []
    except ValueError:
        vals = []
    if not vals or not all(np.isfinite(vals)):
        raise ValueError(f"--panel must be Y0:Y1:X0:X1=REFL[,REFL...] with finite reflectances, got {text!r}")
    return parse_roi(roi), vals[0] if len(vals) == 1 else vals


def read_coefficients(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(gain, offset) from an ELM coefficients JSON (``--save-coefficients``), one-line errors otherwise."""
    coef_path = check_input_file(path, "--coefficients", (".json",))
    try:
        doc = json.loads(coef_path.read_text())
        return np.asarray(doc["gain"], np.float64), np.asarray(doc["offset"], np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"cannot read --coefficients {path!r}: {one_line(e)}") from None


def write_mask_png(path: str | os.PathLike, mask: np.ndarray) -> None:
    """A greyscale PNG of a boolean (H, W) mask (skin white), written atomically (``io.write_png``)."""
    write_png(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


def calibrate_parser() -> Parser:
    """The ``torchskin calibrate`` argument parser."""
    ap = Parser(prog="torchskin calibrate", description="Signals (DN or radiance) to reflectance "
                                 "with the empirical line through reference panels in the frame (numpy only).")
    ap.add_argument("--cube", required=True, help=".npy signal cube (bands, H, W), or (B, bands, H, W) with "
                    "--coefficients")
    ap.add_argument("--panel", action="append", default=[], metavar="Y0:Y1:X0:X1=REFL",
                    help="a reference panel: pixel region and reflectance (one value, or one per band separated by "
                         "commas); repeat for each panel (at least 2)")
    ap.add_argument("--coefficients", help="apply a saved gain/offset JSON instead of fitting panels")
    ap.add_argument("--erode", type=int, default=1, help="pixels dropped on every side of a panel region (default 1)")
    ap.add_argument("--out", required=True, help="reflectance cube .npy (float32)")
    ap.add_argument("--save-coefficients", help="write the fitted gain/offset JSON (for later frames)")
    ap.add_argument("--max-megapixels", type=float, default=MAX_MEGAPIXELS,
                    help=f"refuse frames larger than this (default {MAX_MEGAPIXELS:g})")
    ap.add_argument("--json", action="store_true")
    return ap


def cli_calibrate(argv: list[str]) -> int:
    """``torchskin calibrate --cube DN.npy (--panel Y0:Y1:X0:X1=REFL ... | --coefficients ELM.json) --out
    REFL.npy [--save-coefficients ELM.json] [--erode PX] [--json]`` (numpy only)."""
    args = calibrate_parser().parse_args(argv)
    if bool(args.panel) == bool(args.coefficients):
        raise ValueError("give either --panel (at least twice) or --coefficients")
    out = check_output_file(args.out, "--out", (".npy",))
    save_coef = check_output_file(args.save_coefficients, "--save-coefficients", (".json",)) \
        if args.save_coefficients else None
    cube = load_cube(args.cube, "--cube", args.max_megapixels)
    if args.coefficients:
        gain, offset = read_coefficients(args.coefficients)
        fit = None
    else:
        panels = [parse_panel(p) for p in args.panel]  # (region, reflectance)
        if cube.ndim != 3:
            raise ValueError(f"fitting panels needs one frame (bands, H, W), got shape {cube.shape}")
        fit = elm_fit(cube, panels, args.erode)
        gain, offset = fit["gain"], fit["offset"]
    refl = elm_apply(cube, gain, offset)
    if not np.isfinite(refl).all():
        raise ValueError("the calibrated cube holds NaN or infinite values (check the coefficients)")
    coef = {"gain": gain.tolist(), "offset": offset.tolist()}
    if fit is not None:
        coef["panels"] = [{"region": list(roi), "reflectance": r.tolist(), "signal": s.tolist()}
                          for (roi, _), r, s in zip(panels, fit["references"], fit["signals"])]
        coef["residual"] = fit["residual"].tolist()
    coef_text = json.dumps(coef, indent=1)  # everything prepared before the first file is written
    save_npy(out, refl)
    if save_coef is not None:
        write_text(save_coef, coef_text)
    res = {**coef, "out": args.out, "shape": list(refl.shape),
           "reflectance_range": [float(refl.min()), float(refl.max())]}
    if args.json:
        print(json.dumps(res))
    else:
        print(f"wrote {args.out} {tuple(refl.shape)}: reflectance {res['reflectance_range'][0]:.4f} .. "
              f"{res['reflectance_range'][1]:.4f}; gain " + ", ".join(f"{v:.5g}" for v in gain)
              + "; offset " + ", ".join(f"{v:.5g}" for v in offset)
              + ("" if fit is None else "; residual " + ", ".join(f"{v:.3g}" for v in fit["residual"])))
    return 0


def detect_parser() -> Parser:
    """The ``torchskin detect`` argument parser."""
    ap = Parser(prog="torchskin detect", description="Skin mask of a reflectance cube with the "
                                 "exported detector (numpy + onnxruntime, no torch).")
    ap.add_argument("--model", required=True, help="detector.onnx")
    ap.add_argument("--cube", required=True, help=".npy reflectance cube (4, H, W) or (B, 4, H, W), float32")
    ap.add_argument("--sun-zenith", type=float, help="degrees")
    ap.add_argument("--camera-zenith", type=float, help="degrees")
    ap.add_argument("--relative-azimuth", type=float, help="degrees, |sun - camera azimuth| in [0, 180]")
    ap.add_argument("--range", type=float, help="metres (if the model uses it)")
    ap.add_argument("--out", help="mask PNG (first frame)")
    ap.add_argument("--clip-negative", action="store_true",
                    help="set negative reflectance (noise on dark pixels) to 0 and report how many values were "
                         "clipped, instead of refusing the cube")
    ap.add_argument("--min-reflectance", type=float, default=None,
                    help="pixels whose mean reflectance over the bands is not above this are never skin (their "
                         "indices are noise); default: the floor the model was evaluated with (its metadata "
                         "min_reflectance; 0 for models without it)")
    ap.add_argument("--max-megapixels", type=float, default=MAX_MEGAPIXELS,
                    help=f"refuse frames larger than this (default {MAX_MEGAPIXELS:g})")
    ap.add_argument("--json", action="store_true")
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
        values.append(v)
    return values


def cli_detect(argv: list[str]) -> int:
    """``torchskin detect --model detector.onnx --cube CUBE.npy --sun-zenith DEG --camera-zenith DEG
    --relative-azimuth DEG [--range M] [--out MASK.png] [--json]`` (numpy + onnxruntime only)."""
    args = detect_parser().parse_args(argv)
    mask_path = check_output_file(args.out, "--out", (".png",)) if args.out else None
    det = OnboardDetector(check_input_file(args.model, "--model", (".onnx",)))
    cube = load_cube(args.cube, "--cube", args.max_megapixels)
    if cube.ndim == 3:
        cube = cube[None]
    values = configuration_values(args, det.features)
    out = det(cube, np.tile(np.array(values, dtype=np.float64), (cube.shape[0], 1)),
              negative="clip" if args.clip_negative else "error", min_reflectance=args.min_reflectance)
    if mask_path is not None:
        write_mask_png(mask_path, out["mask"][0])
    frac = float(out["mask"].mean())
    clipped = out.get("clipped_values")
    if args.json:
        res = {"skin_fraction": frac, "skin_pixels": int(out["mask"].sum()),
               "out_of_domain": out["out_of_domain"].tolist(), "shape": list(out["mask"].shape)}
        if clipped is not None:
            res["clipped_values"] = clipped.tolist()
        print(json.dumps(res))
    else:
        flag = " (configuration OUTSIDE the training domain)" if out["out_of_domain"].any() else ""
        clip = f"; {int(clipped.sum())} negative values clipped to 0" if clipped is not None else ""
        print(f"skin pixels {int(out['mask'].sum())} of {out['mask'].size} ({frac:.4f}){flag}{clip}")
    return 0

