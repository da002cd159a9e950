"""``torchskin light``: a light model's diffuse over direct horizontal irradiance per band and sun zenith, and
the direct beam's colour."""

from __future__ import annotations

import argparse
import dataclasses
import json

from ..bands import DEFAULT_BANDS, parse_bands
from .options import (
    add_atmosphere,
    add_bands,
    add_illumination,
    add_json,
    add_sky,
    atmosphere_from_args,
    check_angle,
    check_atmosphere,
    check_number,
)


def cmd_light(args: argparse.Namespace) -> int:
    """Per sun zenith: the light model's diffuse / direct horizontal irradiance per band, and the direct beam's
    first-band / last-band ratio (how red the low sun is)."""
    from ..render.light import light_tables
    from ..render.scene import Sun

    check_atmosphere(argparse.Namespace(**{**vars(args), "source_zenith": 0.0}))
    try:
        zeniths = [float(z) for z in args.zenith.split(",")]
    except ValueError:
        raise ValueError(f"--zenith must be comma-separated degrees, got {args.zenith!r}") from None
    check_number("--sky", args.sky, 0, 1)
    for z in zeniths:
        check_angle("--zenith", z, 0, 90)
        if not z < 90:  # no direct light on a horizontal surface: the ratio is undefined
            raise ValueError(f"--zenith must be below 90 degrees (a sun above the horizon), got {z:g}")
    bands = parse_bands(args.bands) if args.bands else DEFAULT_BANDS
    atm = atmosphere_from_args(args)
    t = light_tables(args.illumination, [Sun(zenith_deg=z, atmosphere=atm, sky_fraction=args.sky) for z in zeniths],
                     bands)
    ratio = (t.diffuse_horizontal / t.direct_horizontal).tolist()
    red = (t.direct_horizontal[:, 0] / t.direct_horizontal[:, -1]).tolist()
    spectrl2 = args.illumination == "spectrl2"
    if args.json:
        print(json.dumps({**t.summary(bands), "zenith_deg": zeniths, "diffuse_over_direct": ratio,
                          "direct_first_over_last": red,
                          **({"atmosphere": dataclasses.asdict(atm)} if spectrl2 else {"sky_fraction": args.sky})}))
        return 0
    names = [f"{b.center_nm:g} nm" for b in bands]
    print(f"{'sun zenith':>10}" + "".join(f"{n:>10}" for n in names) + f"{'direct ' + names[0] + '/' + names[-1]:>22}")
    for z, row, r in zip(zeniths, ratio, red):
        print(f"{z:>9g}°" + "".join(f"{x:>10.3f}" if abs(x) < 1 else f"{x:>10.3g}" for x in row) + f"{r:>22.2f}")
    print(f"diffuse / direct horizontal irradiance ({args.illumination}: aerosol {atm.aerosol_500nm:g} at 500 nm, "
          f"water {atm.precipitable_water_cm:g} cm, ozone {atm.ozone_atm_cm:g} atm-cm, {atm.pressure_pa:g} Pa, "
          f"day {atm.day_of_year})" if spectrl2 else
          f"diffuse / direct horizontal irradiance ({args.illumination}: a blackbody sun and a grey sky of "
          f"{args.sky:g} times it; the atmosphere options do not apply)")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin light`` command."""
    lp = sub.add_parser("light", help="the light model's direct and diffuse irradiance per band and sun zenith",
                        description="Tabulate a light model (render.light): diffuse over direct horizontal "
                                    "irradiance per band, and the direct beam's colour, per sun zenith.")
    lp.add_argument("--zenith", default="10,45,60,75,85", help="sun zeniths, degrees (default 10,45,60,75,85)")
    add_bands(lp)
    add_illumination(lp)
    add_atmosphere(lp)
    add_sky(lp)
    add_json(lp)
    lp.set_defaults(func=cmd_light)
    return lp
