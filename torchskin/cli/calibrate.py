"""``torchskin calibrate``: signals (DN or radiance) to reflectance with the empirical line (ELM) through
reference panels in the frame, numpy only (``torchskin.cli.main`` dispatches here without importing torch; the
ELM itself is ``torchskin.onboard``)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..cubefiles import CUBE_SUFFIXES, cube_format
from ..errors import Parser, check_input_file, check_output_file, one_line
from ..io import bands_sidecar_text, npy_header, read_bands_sidecar, save_npy, sidecar_path, write_text
from ..onboard import calibrate_file, elm_apply, elm_fit
from .cubes import load_cube
from .options import add_json, add_max_megapixels, add_out_file, add_tile_rows

PROG = "torchskin calibrate"
DESCRIPTION = ("Signals (DN or radiance) to reflectance with the empirical line through reference panels in the "
               "frame (numpy only).")
HELP = "signals to reflectance with ELM through panel regions (numpy only)"


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


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The ``torchskin calibrate`` options."""
    ap.add_argument("--cube", required=True, help="signal cube: .npy (bands, H, W), or (B, bands, H, W) with "
                    "--coefficients; an ENVI .hdr (with its data file) or a multi-band GeoTIFF .tif")
    ap.add_argument("--panel", action="append", default=[], metavar="Y0:Y1:X0:X1=REFL",
                    help="a reference panel: pixel region and reflectance (one value, or one per band separated by "
                         "commas); repeat for each panel (at least 2)")
    ap.add_argument("--coefficients", help="apply a saved gain/offset JSON instead of fitting panels")
    ap.add_argument("--erode", type=int, default=1, help="pixels dropped on every side of a panel region (default 1)")
    add_out_file(ap, "the reflectance cube (float32) in the input's format: .npy (+ sidecar), .hdr (ENVI, with a "
                     ".img beside it) or .tif (GeoTIFF, the input's georeferencing kept)")
    add_tile_rows(ap)
    ap.add_argument("--save-coefficients", help="write the fitted gain/offset JSON (for later frames)")
    add_max_megapixels(ap)
    add_json(ap)


def calibrate_parser() -> Parser:
    """The ``torchskin calibrate`` argument parser, on its own (the torch-free path)."""
    ap = Parser(prog=PROG, description=DESCRIPTION)
    add_arguments(ap)
    return ap


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin calibrate`` entry of the full parser (the same options as ``calibrate_parser``)."""
    ap: argparse.ArgumentParser = sub.add_parser("calibrate", help=HELP, description=DESCRIPTION)
    add_arguments(ap)
    ap.set_defaults(func=cmd_calibrate)
    return ap


def cli_calibrate(argv: list[str]) -> int:
    """``torchskin calibrate --cube DN.npy (--panel Y0:Y1:X0:X1=REFL ... | --coefficients ELM.json) --out
    REFL.npy [--save-coefficients ELM.json] [--erode PX] [--json]`` (numpy only)."""
    return cmd_calibrate(calibrate_parser().parse_args(argv))


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Run ``torchskin calibrate`` on parsed options."""
    if bool(args.panel) == bool(args.coefficients):
        raise ValueError("give either --panel (at least twice) or --coefficients")
    check_input_file(args.cube, "--cube", CUBE_SUFFIXES)  # before --out's suffix, which follows the cube's
    fmt = cube_format(args.cube)
    suffixes = {"npy": (".npy",), "envi": (".hdr",), "tiff": (".tif", ".tiff")}[fmt]
    if not str(args.out).lower().endswith(suffixes):
        raise ValueError(f"--out {args.out!r} must end in {' or '.join(suffixes)}: calibrate writes its input's "
                         f"format ({ {'npy': '.npy', 'envi': 'ENVI', 'tiff': 'GeoTIFF'}[fmt] }, as --cube)")
    out = check_output_file(args.out, "--out", suffixes)
    save_coef = check_output_file(args.save_coefficients, "--save-coefficients", (".json",)) \
        if args.save_coefficients else None
    if fmt != "npy" or len(_npy_shape(args.cube)) == 3:
        return _calibrate_stream(args, out, save_coef)
    cube = load_cube(args.cube, "--cube", args.max_megapixels)
    bands = read_bands_sidecar(args.cube)  # the input's wavelengths go with the output
    n_bands = cube.shape[0] if cube.ndim == 3 else cube.shape[1]
    if bands is not None and len(bands) != n_bands:
        raise ValueError(f"the sidecar {str(sidecar_path(args.cube))!r} gives {len(bands)} bands, but --cube "
                         f"{args.cube!r} holds {n_bands}")
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
    out_sidecar = sidecar_path(out)
    if bands is not None:
        write_text(out_sidecar, bands_sidecar_text(bands, quantity="reflectance"))
    elif out_sidecar.is_file():  # an earlier output's wavelengths do not describe this one
        out_sidecar.unlink()
    if save_coef is not None:
        write_text(save_coef, coef_text)
    res = {**coef, "out": args.out, "shape": list(refl.shape),
           "reflectance_range": [float(refl.min()), float(refl.max())]}
    if args.json:
        print(json.dumps(res))
    else:
        print(fit_summary(args.out, refl.shape, res["reflectance_range"], gain, offset,
                          None if fit is None else fit["residual"]))
    return 0


#: up to this many bands, calibrate's summary line lists gain, offset and residual band by band; above, their ranges
LIST_BANDS = 8


def fit_summary(out: Any, shape: Sequence[int], reflectance_range: Sequence[float], gain: np.ndarray,
                offset: np.ndarray, residual: np.ndarray | None) -> str:
    """calibrate's one summary line: the file written, its shape and reflectance range, and the line's gain,
    offset and residual per band (``LIST_BANDS`` bands or fewer) or their ranges (a hyperspectral cube's 121
    bands; ``--json`` and ``--save-coefficients`` give every band)."""
    lo, hi = reflectance_range
    head = f"wrote {out} {tuple(shape)}: reflectance {lo:.4f} .. {hi:.4f}; "
    if len(gain) <= LIST_BANDS:
        return (head + "gain " + ", ".join(f"{v:.5g}" for v in gain) + "; offset "
                + ", ".join(f"{v:.5g}" for v in offset)
                + ("" if residual is None else "; residual " + ", ".join(f"{v:.4f}" for v in residual)))
    return (head + f"over its {len(gain)} bands gain {gain.min():.5g} .. {gain.max():.5g}, offset "
            f"{offset.min():.5g} .. {offset.max():.5g}"
            + ("" if residual is None else f", residual at most {np.max(residual):.4f}")
            + " (every band: --json or --save-coefficients)")


def _npy_shape(path: str) -> tuple[int, ...]:
    try:
        return npy_header(path)[0]
    except (OSError, ValueError, EOFError, SyntaxError):
        return ()  # load_cube gives the one-line error


def _calibrate_stream(args: argparse.Namespace, out: Any, save_coef: Any) -> int:
    """``torchskin calibrate`` of one frame, streamed in row tiles (``onboard.calibrate_file``), written in the
    input's format."""
    coefficients = read_coefficients(args.coefficients) if args.coefficients else None
    panels = [parse_panel(p) for p in args.panel] if args.panel else None
    res = calibrate_file(args.cube, out, panels, coefficients, args.erode, args.tile_rows,
                         max_megapixels=args.max_megapixels)
    gain, offset, fit = res["gain"], res["offset"], res["fit"]
    coef: dict[str, Any] = {"gain": gain.tolist(), "offset": offset.tolist()}
    if fit is not None and panels is not None:
        coef["panels"] = [{"region": list(roi), "reflectance": r.tolist(), "signal": s.tolist()}
                          for (roi, _), r, s in zip(panels, fit["references"], fit["signals"])]
        coef["residual"] = fit["residual"].tolist()
    if save_coef is not None:
        write_text(save_coef, json.dumps(coef, indent=1))
    doc = {**coef, "out": res["out"], "shape": res["shape"], "reflectance_range": res["reflectance_range"]}
    if args.json:
        print(json.dumps(doc))
    else:
        print(fit_summary(res["out"], res["shape"], res["reflectance_range"], gain, offset,
                          None if fit is None else fit["residual"]))
    return 0
