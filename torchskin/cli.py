"""The ``torchskin`` command line."""

from __future__ import annotations

import argparse
import json
import math
import sys

import torch

from . import __version__, tissue
from .bands import DEFAULT_BANDS, band_sampling, parse_bands
from .detect import DEFAULT_BOX, indices, rules_detector


# ------------------------------------------------------------------------------------------------ spectra
def _parse_params(items: list[str]) -> dict[str, float]:
    out = {}
    for it in items:
        name, sep, val = it.partition("=")
        name = name.strip()
        if not sep:
            raise ValueError(f"--param needs NAME=VALUE, got {it!r}")
        if name not in tissue.PARAM_NAMES:
            raise ValueError(f"--param: unknown parameter {name!r}; known: {', '.join(tissue.PARAM_NAMES)}")
        try:
            out[name] = float(val)
        except ValueError:
            raise ValueError(f"--param {name}: {val!r} is not a number") from None
    return out


def _parse_wavelengths(text: str) -> torch.Tensor:
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"--wavelengths must be START:STOP:STEP in nm, got {text!r}")
    try:
        start, stop, step = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--wavelengths must be numbers START:STOP:STEP, got {text!r}") from None
    return tissue.wavelength_grid(start, stop, step, dtype=torch.float64)


def _skins(args) -> tuple[tissue.SkinParams, list[str]]:
    overrides = _parse_params(args.param or [])
    names: list[str] = []
    for p in args.preset or []:
        names.extend(x for x in p.split(",") if x)
    if args.all_presets:
        names.extend(n for n in tissue.PRESETS if n not in names)
    parts, labels = [], []
    if names:
        parts.append(tissue.preset(names, dtype=torch.float64))
        labels.extend(names)
    if args.sample:
        s, types = tissue.sample(args.sample, args.seed, dtype=torch.float64)
        parts.append(s)
        labels.extend(f"sample{k}:{t}" for k, t in enumerate(types))
    if not parts:
        if overrides:  # one skin: the defaults with the given parameters
            parts.append(tissue.SkinParams.create(dtype=torch.float64))
            labels.append("custom")
        else:  # default: every preset
            parts.append(tissue.preset(list(tissue.PRESETS), dtype=torch.float64))
            labels.extend(tissue.PRESETS)
    skins = tissue.SkinParams.cat(parts)
    if overrides:
        skins = skins.replace(**{k: torch.full_like(skins.melanosome, v) for k, v in overrides.items()})
        skins.validate()
    return skins, labels


def cmd_spectra(args) -> int:
    if args.sample is not None and args.sample < 1:
        raise ValueError(f"--sample must be >= 1, got {args.sample}")
    if not (0.0 <= args.incidence_deg < 90.0):
        raise ValueError(f"--incidence-deg must lie in [0, 90), got {args.incidence_deg}")
    skins, labels = _skins(args)
    theta = math.radians(args.incidence_deg)
    if args.bands:
        bands = parse_bands(args.bands)
        grid, W = band_sampling(bands, dtype=torch.float64)
        wl_out = torch.tensor([b.center_nm for b in bands], dtype=torch.float64)
        R = tissue.reflectance(skins, grid, theta_i=theta) @ W
    else:
        wl_out = _parse_wavelengths(args.wavelengths) if args.wavelengths else tissue.wavelength_grid(
            400, 1700, 10, dtype=torch.float64)
        R = tissue.reflectance(skins, wl_out, theta_i=theta)
    Rb = tissue.reflectance(skins, torch.tensor([b.center_nm for b in DEFAULT_BANDS], dtype=torch.float64),
                            theta_i=theta)
    g, s = indices(Rb)
    inside = rules_detector(g, s, DEFAULT_BOX)
    pdict = skins.as_dict()
    if args.json:
        out = {"skins": [
            {"name": labels[k], "params": {n: pdict[n][k] for n in tissue.PARAM_NAMES},
             "wavelengths_nm": wl_out.tolist(), "reflectance": R[k].tolist(), "ndgri": float(g[k]),
             "ndsi": float(s[k]), "inside_box": bool(inside[k])}
            for k in range(len(labels))
        ], "incidence_deg": args.incidence_deg, "box": DEFAULT_BOX.as_dict()}
        print(json.dumps(out))
    else:
        head = f"{'skin':<14}{'mel':>6}{'blood':>6}{'oxy':>6}  " + "".join(
            f"{b.center_nm:>7g}" for b in DEFAULT_BANDS) + f"{'NDGRI':>9}{'NDSI':>8}  box"
        print(head)
        for k in range(min(len(labels), 50)):
            print(f"{labels[k]:<14}{pdict['melanosome'][k]:>6.3f}{pdict['blood'][k]:>6.2f}"
                  f"{pdict['oxygenation'][k]:>6.2f}  " + "".join(f"{x:>7.3f}" for x in Rb[k].tolist())
                  + f"{float(g[k]):>9.3f}{float(s[k]):>8.3f}  {'in' if inside[k] else 'OUT'}")
        if len(labels) > 50:
            print(f"... {len(labels) - 50} more (use --json)")
        if len(labels) > 1:
            q = torch.tensor([0.005, 0.995], dtype=g.dtype)
            qg, qs = torch.quantile(g, q), torch.quantile(s, q)
            print(f"NDGRI 0.5/99.5 %: {qg[0]:.4f} {qg[1]:.4f} (box {DEFAULT_BOX.b1}, {DEFAULT_BOX.b2});"
                  f" NDSI: {qs[0]:.4f} {qs[1]:.4f} (box {DEFAULT_BOX.c1}, {DEFAULT_BOX.c2});"
                  f" inside: {int(inside.sum())}/{len(labels)}")
    if args.plot:
        from .plots import plot_spectra

        wl_plot = tissue.wavelength_grid(400, 1700, 2, dtype=torch.float64)
        plot_spectra(args.plot, wl_plot, tissue.reflectance(skins, wl_plot, theta_i=theta), labels, g, s,
                     title=f"Diffuse skin reflectance, incidence {args.incidence_deg:g}°",
                     shade=skins.melanosome / 0.45)
        if not args.json:
            print(f"wrote {args.plot}")
    return 0


# -------------------------------------------------------------------------------------------------- bench
def cmd_bench(args) -> int:
    from . import bench

    only = [x.strip() for x in args.only.split(",")] if args.only else None
    res = bench.run(only, compile=args.compile)
    if args.json:
        print(json.dumps(res))
    else:
        for name, r in res.items():
            rate = r.get("samples_x_bands_per_s")
            extra = f"{rate / 1e6:.1f} M skin-wavelengths/s" if rate else ""
            print(f"{name:<14}{extra}  ({r.get('device')}, {r.get('dtype')}, {r.get('seconds', 0):.3f} s)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="torchskin", description="Physics-based multispectral skin toolkit")
    ap.add_argument("--version", action="version", version=f"torchskin {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("spectra", help="diffuse skin reflectance spectra, indices and the rules box",
                        description="Diffuse-model skin reflectance (9-layer Kubelka-Munk + front surface).")
    sp.add_argument("--preset", action="append", metavar="NAME",
                    help=f"preset skin (repeatable or comma separated): {', '.join(tissue.PRESETS)}")
    sp.add_argument("--all-presets", action="store_true", help="every preset")
    sp.add_argument("--sample", type=int, metavar="N", help="N random skins across Fitzpatrick I-VI")
    sp.add_argument("--seed", type=int, default=0, help="seed for --sample (default 0)")
    sp.add_argument("--param", action="append", metavar="NAME=VALUE",
                    help=f"set a parameter for every skin: {', '.join(tissue.PARAM_NAMES)}")
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--wavelengths", metavar="START:STOP:STEP", help="wavelength grid in nm (default 400:1700:10)")
    g.add_argument("--bands", metavar="C[/FWHM],...", help="band centres (and FWHM) in nm, e.g. 544,633,1080,1580")
    sp.add_argument("--incidence-deg", type=float, default=0.0, help="incidence angle in degrees (default 0)")
    sp.add_argument("--json", action="store_true", help="print one JSON object")
    sp.add_argument("--plot", metavar="PNG", help="write spectra 400-1700 nm and the rules plane to PNG")
    sp.set_defaults(func=cmd_spectra)

    bp = sub.add_parser("bench", help="benchmarks (JSON with --json)")
    bp.add_argument("--json", action="store_true")
    bp.add_argument("--only", metavar="NAMES", help="comma-separated benchmark names (default: all)")
    bp.add_argument("--compile", action="store_true", help="also measure the torch.compile path (slow start)")
    bp.set_defaults(func=cmd_bench)
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as e:
        print(f"torchskin {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
