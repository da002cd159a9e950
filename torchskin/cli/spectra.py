"""``torchskin spectra``: diffuse skin reflectance spectra, NDGRI / NDSI and the rules box, for presets, random
skins or given parameters."""

from __future__ import annotations

import argparse
import json
import math

import torch

from .. import tissue
from ..bands import DEFAULT_BANDS, band_sampling, parse_bands, range_numbers
from ..detect import DEFAULT_BOX, indices, rules_detector
from ..errors import check_output_file
from .options import add_bands, add_json, add_seed

#: the largest ``--sample``
MAX_SAMPLE = 10_000_000


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
    """The ``--wavelengths`` grid: a range as ``--bands`` writes one (``bands.range_numbers``), sampled by
    ``tissue.wavelength_grid`` (STOP included, up to ``bands.MAX_GRID_POINTS`` wavelengths)."""
    return tissue.wavelength_grid(*range_numbers(text, "--wavelengths"), dtype=torch.float64)


def _skins(args: argparse.Namespace) -> tuple[tissue.SkinParams, list[str]]:
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


def cmd_spectra(args: argparse.Namespace) -> int:
    """Run ``torchskin spectra``: a table (or ``--json``, ``--plot``) of the chosen skins' reflectance, NDGRI,
    NDSI and whether the rules box holds them."""
    if args.plot:
        check_output_file(args.plot, "--plot", (".png",))
    if args.sample is not None and not (1 <= args.sample <= MAX_SAMPLE):
        raise ValueError(f"--sample must lie in [1, {MAX_SAMPLE}], got {args.sample}")
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
        # the table shows the requested bands (--bands), else the four index bands; NDGRI and NDSI always come
        # from 544, 633, 1080 and 1580 nm
        cols, vals = (wl_out.tolist(), R) if args.bands else ([b.center_nm for b in DEFAULT_BANDS], Rb)
        if len(cols) > 12:
            cols, vals = [b.center_nm for b in DEFAULT_BANDS], Rb  # a long grid: see --json or --plot
        width = max([7] + [len(f"{c:g}") + 1 for c in cols])  # a column per band, wide enough for its centre
        head = f"{'skin':<14}{'mel':>6}{'blood':>6}{'oxy':>6}  " + "".join(
            f"{c:>{width}g}" for c in cols) + f"{'NDGRI':>9}{'NDSI':>8}  box"
        print(head)
        for k in range(min(len(labels), 50)):
            print(f"{labels[k]:<14}{pdict['melanosome'][k]:>6.3f}{pdict['blood'][k]:>6.2f}"
                  f"{pdict['oxygenation'][k]:>6.2f}  " + "".join(f"{x:>{width}.3f}" for x in vals[k].tolist())
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
        from ..plots import plot_spectra

        wl_plot = tissue.wavelength_grid(400, 1700, 2, dtype=torch.float64)
        plot_spectra(args.plot, wl_plot, tissue.reflectance(skins, wl_plot, theta_i=theta), labels, g, s,
                     title=f"Diffuse skin reflectance, incidence {args.incidence_deg:g}°",
                     shade=skins.melanosome / 0.45)
        if not args.json:
            print(f"wrote {args.plot}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin spectra`` command."""
    sp = sub.add_parser("spectra", help="diffuse skin reflectance spectra, indices and the rules box",
                        description="Diffuse-model skin reflectance (9-layer Kubelka-Munk + front surface).")
    sp.add_argument("--preset", action="append", metavar="NAME",
                    help=f"preset skin (repeatable or comma separated): {', '.join(tissue.PRESETS)}")
    sp.add_argument("--all-presets", action="store_true", help="every preset")
    sp.add_argument("--sample", type=int, metavar="N", help="N random skins across Fitzpatrick I-VI")
    add_seed(sp, "--sample")
    sp.add_argument("--param", action="append", metavar="NAME=VALUE",
                    help=f"set a parameter for every skin: {', '.join(tissue.PARAM_NAMES)}")
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--wavelengths", metavar="START:STOP:STEP", help="wavelength grid in nm (default 400:1700:10)")
    add_bands(g, default="the --wavelengths grid")
    sp.add_argument("--incidence-deg", type=float, default=0.0, help="incidence angle in degrees (default 0)")
    add_json(sp)
    sp.add_argument("--plot", metavar="PNG", help="write spectra 400-1700 nm and the rules plane to PNG")
    sp.set_defaults(func=cmd_spectra)
    return sp
