"""Options that several ``torchskin`` commands share, each defined once, with the checks that go with them.

An option's flag, type, default and help text are written here and nowhere else, so ``--device`` (say) reads
the same under every command that takes it. The choices that come from a registry are read from it when the
parser is built: the panel kinds (``render.scene.PANEL_KINDS``), the skin BRDF kinds (the ``skin-<surface>``
entries with a BRDF in ``render.materials.KINDS``) and the light models (``render.light.MODELS``), so a kind
registered there appears in the command line without an edit here.

This module imports neither torch nor the renderer at import time (the torch-free ``detect`` and ``calibrate``
use it); the builders that read a torch-side registry import it when called.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
from typing import Any

from ..io import MAX_MEGAPIXELS

#: what ``add_argument`` is called on: a parser or one of its (mutually exclusive) groups
ArgumentTarget = argparse._ActionsContainer


JSON_HELP = "print one JSON object (no progress output)"
DEVICE_HELP = "torch device for shading (cpu, cuda, cuda:N, mps; default cpu)"
SURFACE_HELP = ("skin surface model of eq 3.1.1's diffuse term: thesis (default; rho_d includes the front surface, "
                "as the thesis defines it and its measured images support) or conserving (subsurface part only; "
                "energy-conserving)")
BANDS_METAVAR = "C[/FWHM],..."
BANDS_HELP = ("band centres and optional FWHM in nm, e.g. 544,633,1080/20,1580/40 (no FWHM: "
              "monochromatic), ranges START:STOP:STEP[/FWHM], e.g. 450:1650:10 (450, 460, ..., 1650), a named "
              "camera (rededge-mx, thesis), or a response table FILE.csv (wavelength_nm, then one column per band)")

#: the atmosphere options (``render``, ``light``) -> ``scene.Atmosphere`` fields
ATMOSPHERE_OPTIONS = {"--aerosol": "aerosol_500nm", "--water": "precipitable_water_cm", "--ozone": "ozone_atm_cm",
                      "--pressure": "pressure_pa", "--day-of-year": "day_of_year"}
#: what each atmosphere option is (its default comes from ``scene.Atmosphere``, its range from
#: ``scene.ATMOSPHERE_RANGES``)
_ATMOSPHERE = {"--aerosol": "aerosol optical depth at 500 nm", "--water": "precipitable water, cm",
               "--ozone": "ozone column, atm-cm", "--pressure": "surface pressure, Pa", "--day-of-year": "day of year"}
#: a phrase for the light models the help text knows; a newly registered model is listed by name alone
LIGHT_MODEL_NOTES = {"spectrl2": "clear-sky sun, sky and ground-reflected light from the atmosphere below, "
                                 "via pvlib",
                     "thesis": "a 5950 K blackbody sun and a grey sky of --sky"}
#: a phrase for the panel kinds the help text knows; a newly added kind is listed by name alone
PANEL_NOTES = {"lambertian": "0.97 and 0.03", "spectralon": "Table 3 DHR", "spectralon-brdf": "Table 3 DHR with "
               "the Spectralon-like BRDF"}


# ------------------------------------------------------------------------------------------------ registries
def panel_kinds() -> tuple[str, ...]:
    """The reference-panel kinds ``render.scene.panel_materials`` builds (``scene.PANEL_KINDS``)."""
    from ..render.scene import PANEL_KINDS

    return tuple(PANEL_KINDS)


def surface_models() -> tuple[str, ...]:
    """The skin surface models: every ``skin-<surface>`` entry of the material registry
    (``render.materials.KINDS``) that has a BRDF (``skin-diffuse``, the diffuse model alone, has none)."""
    from ..render.materials import KINDS

    return tuple(name.removeprefix("skin-") for name, kind in KINDS.items()
                 if name.startswith("skin-") and kind.brdf is not None)


def light_models() -> tuple[str, ...]:
    """The light models of ``render.light.MODELS``, in registration order."""
    from ..render.light import MODELS

    return tuple(MODELS)


# ---------------------------------------------------------------------------------------------- the options
def add_json(p: ArgumentTarget) -> None:
    """``--json``: print one JSON object instead of the text summary."""
    p.add_argument("--json", action="store_true", help=JSON_HELP)


def add_device(p: ArgumentTarget) -> None:
    """``--device``: the torch device for shading (checked by ``devices.check_device`` before any work)."""
    p.add_argument("--device", default="cpu", help=DEVICE_HELP)


def add_out_folder(p: ArgumentTarget, contents: str) -> None:
    """``--out`` (required): the folder a command writes ``contents`` into."""
    p.add_argument("--out", required=True, help=f"output folder: {contents}")


def add_overwrite(p: ArgumentTarget, what: str) -> None:
    """``--overwrite``: write into an ``--out`` folder that is not empty, replacing ``what`` (without it the
    command refuses such a folder: ``errors.check_output_folder(..., overwrite=...)``)."""
    p.add_argument("--overwrite", action="store_true",
                   help=f"write into an --out folder that is not empty, replacing {what}; without it such a folder "
                        "is refused")


def add_out_file(p: ArgumentTarget, contents: str, required: bool = True) -> None:
    """``--out``: the file a command writes (``contents`` says what and in which format)."""
    p.add_argument("--out", required=required, help=f"output file: {contents}")


def add_seed(p: ArgumentTarget, of: str) -> None:
    """``--seed`` (a non-negative integer, default 0): the seed of ``of``."""
    p.add_argument("--seed", type=int, default=0, help=f"seed of {of} (default 0)")


def add_surface(p: ArgumentTarget, lead: str = "", from_config: bool = False) -> None:
    """``--surface``: a skin surface model (``surface_models()``, default ``optics.DEFAULT_SURFACE``, or none
    with ``from_config``: the dataset configuration's then); ``lead`` says what the option sets where that is
    more than the model of the whole render."""
    from ..optics import DEFAULT_SURFACE

    p.add_argument("--surface", choices=surface_models(), default=None if from_config else DEFAULT_SURFACE,
                   help=(f"{lead}; " if lead else "") + SURFACE_HELP)


def add_panels(p: ArgumentTarget, note: str = "") -> None:
    """``--panels``: the reference panels' kind (``panel_kinds()``, default lambertian)."""
    kinds = panel_kinds()
    listed = ", ".join(f"{k} ({PANEL_NOTES[k]})" if k in PANEL_NOTES else k for k in kinds)
    p.add_argument("--panels", choices=kinds, default="lambertian",
                   help=f"reference panels: {listed}; default lambertian" + (f"; {note}" if note else ""))


def add_illumination(p: ArgumentTarget) -> None:
    """``--illumination``: the light model (``light_models()``, default spectrl2)."""
    from ..render.scene import DEFAULT_ILLUMINATION

    names = light_models()
    listed = "; ".join(f"{n} ({LIGHT_MODEL_NOTES[n]})" if n in LIGHT_MODEL_NOTES else n for n in names)
    p.add_argument("--illumination", choices=names, default=DEFAULT_ILLUMINATION, metavar="MODEL",
                   help=f"light model (render.light): {listed}; default {DEFAULT_ILLUMINATION}")


def add_atmosphere(p: ArgumentTarget) -> None:
    """The spectrl2 atmosphere options (``ATMOSPHERE_OPTIONS``), with the defaults of ``scene.Atmosphere`` and
    the ranges of ``scene.ATMOSPHERE_RANGES``."""
    from ..render.scene import ATMOSPHERE_RANGES, Atmosphere

    defaults = {f.name: f.default for f in dataclasses.fields(Atmosphere)}
    for opt, what in _ATMOSPHERE.items():
        key = ATMOSPHERE_OPTIONS[opt]
        lo, hi = ATMOSPHERE_RANGES[key]
        default = defaults[key]
        p.add_argument(opt, type=type(default), default=default,
                       help=f"spectrl2: {what}, {lo:g}-{hi:g} (default {default:g})")


def add_sky(p: ArgumentTarget) -> None:
    """``--sky``: the thesis light model's sky-to-sun irradiance ratio."""
    p.add_argument("--sky", type=float, default=0.1,
                   help="thesis: sky irradiance / sun irradiance, 0-1 (default 0.1; spectrl2 computes its sky)")


def band_list_text(text: str) -> str:
    """An argparse ``type`` for ``--bands``: the text as given, unless it names no band at all (empty or blank),
    which is a usage error rather than the default bands (the commands read an absent ``--bands`` as None).

    >>> band_list_text("544,1580")
    '544,1580'
    >>> band_list_text(" ")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: expected at least one band (centre[/fwhm],... in nm), got ' '
    """
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected at least one band (centre[/fwhm],... in nm), got {text!r}")
    return text


def add_bands(p: ArgumentTarget, default: str = "544,633,1080,1580") -> None:
    """``--bands``: band centres (and FWHM) in nm (``bands.BandSet.parse``); ``default`` says what is used
    without it; an empty value is refused (``band_list_text``)."""
    p.add_argument("--bands", type=band_list_text, metavar=BANDS_METAVAR, help=f"{BANDS_HELP} (default: {default})")


def add_frame(p: ArgumentTarget) -> None:
    """``--width``, ``--height`` and ``--max-megapixels`` (checked by ``check_frame``)."""
    p.add_argument("--width", type=int, default=512, help="frame width in pixels (default 512)")
    p.add_argument("--height", type=int, default=512, help="frame height in pixels (default 512)")
    add_max_megapixels(p)


def positive_number(text: str) -> float:
    """An argparse ``type``: a finite number above 0 (the usage error names the option)."""
    import math

    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number above 0, got {text!r}")
    return v


def add_max_megapixels(p: ArgumentTarget) -> None:
    """``--max-megapixels``: the frame cap (``io.MAX_MEGAPIXELS``) that ``render`` and ``experiment`` make and
    ``detect`` and ``calibrate`` read within."""
    p.add_argument("--max-megapixels", type=positive_number, default=MAX_MEGAPIXELS,
                   help=f"refuse frames read whole (a batch of .npy frames, a compressed GeoTIFF) larger than this "
                        f"many megapixels (default {MAX_MEGAPIXELS:g}); a frame streamed from a memory-mapped file "
                        "has no cap")


def add_tile_rows(p: ArgumentTarget) -> None:
    """``--tile-rows``: rows per tile when ``detect`` and ``calibrate`` stream a frame (``onboard.TILE_BYTES``)."""
    p.add_argument("--tile-rows", type=int, default=None,
                   help="rows of the frame read, processed and written at a time (default: about 32 MB of the "
                        "input, bands x rows x width x 4 bytes): peak memory is a few times that, whatever the "
                        "frame's height")


def add_no_noise(p: ArgumentTarget) -> None:
    """``--no-noise``: the sensor without noise."""
    p.add_argument("--no-noise", action="store_true", help="switch sensor noise off")


# ----------------------------------------------------------------------------------------------- the checks
def check_angle(name: str, v: float, lo: float, hi: float) -> None:
    """``ValueError`` naming ``name`` unless ``lo <= v <= hi`` degrees (NaN fails too)."""
    if not (lo <= v <= hi):
        raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}] degrees, got {v:g}")


def check_number(name: str, v: float, lo: float = -math.inf, hi: float = math.inf, what: str = "a number") -> None:
    """``ValueError`` naming ``name`` unless ``v`` is finite and within ``[lo, hi]``.

    >>> check_number("--sky", 0.5, 0, 1)
    >>> check_number("--sky", 2.0, 0, 1)
    Traceback (most recent call last):
    ...
    ValueError: --sky must be a number in [0, 1], got 2
    """
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"{name} must be {what} in [{lo:g}, {hi:g}], got {v:g}")


def check_atmosphere(args: argparse.Namespace) -> None:
    """The atmosphere options within ``scene.ATMOSPHERE_RANGES``; a registered ``--illumination``; a sun above
    the horizon (``args.source_zenith``) for "spectrl2"."""
    from ..render.light import MODELS
    from ..render.scene import ATMOSPHERE_RANGES

    for opt, key in ATMOSPHERE_OPTIONS.items():
        lo, hi = ATMOSPHERE_RANGES[key]
        check_number(opt, getattr(args, opt[2:].replace("-", "_")), lo, hi)
    if args.illumination not in MODELS:
        raise ValueError(f"--illumination must be one of {', '.join(sorted(MODELS))}, got {args.illumination!r}")
    if args.illumination == "spectrl2" and not args.source_zenith < 90:
        raise ValueError(f"--source-zenith must be below 90 degrees for --illumination spectrl2 (a sun above the "
                         f"horizon), got {args.source_zenith:g}")


def atmosphere_from_args(args: argparse.Namespace) -> Any:
    """The ``scene.Atmosphere`` of the atmosphere options."""
    from ..render.scene import Atmosphere

    return Atmosphere(aerosol_500nm=args.aerosol, precipitable_water_cm=args.water, ozone_atm_cm=args.ozone,
                      pressure_pa=args.pressure, day_of_year=args.day_of_year)


def check_frame(args: argparse.Namespace, bands: int, suns: int = 1) -> None:
    """Resolution within the cap (``--max-megapixels``) and an estimate of the memory the frame needs within
    what the machine has."""
    check_number("--max-megapixels", args.max_megapixels, 1e-6, 1e6, "a positive number")
    for name, v in (("--width", args.width), ("--height", args.height)):
        if v < 16:
            raise ValueError(f"{name} must be at least 16 pixels (camera resolution), got {v}")
    mp = args.width * args.height / 1e6
    if mp > args.max_megapixels:
        raise ValueError(f"--width x --height is {mp:.1f} megapixels, above the cap of {args.max_megapixels:g} "
                         "(--max-megapixels raises it)")
    need = args.width * args.height * (400 + 64 * bands * suns)  # G-buffer, shading, sensor and ELM temporaries
    try:
        have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return
    if need > 0.8 * have:
        raise ValueError(f"a {args.width} x {args.height} frame needs about {need / 2**30:.1f} GiB, more than this "
                         f"machine's {have / 2**30:.1f} GiB allows")


__all__ = ["ATMOSPHERE_OPTIONS", "BANDS_HELP", "DEVICE_HELP", "JSON_HELP", "MAX_MEGAPIXELS", "SURFACE_HELP", "add_atmosphere",
           "add_bands", "add_device", "band_list_text", "add_tile_rows", "add_frame", "add_illumination", "add_json", "add_max_megapixels", "add_no_noise", "add_out_file",
           "add_out_folder", "add_overwrite", "add_panels", "add_seed", "add_sky", "add_surface", "atmosphere_from_args",
           "check_angle", "check_atmosphere", "check_frame", "check_number", "light_models", "panel_kinds",
           "surface_models"]
