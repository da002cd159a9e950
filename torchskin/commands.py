"""The ``torchskin`` commands (everything but the torch-free ``detect``, see ``torchskin.cli``)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from typing import Any

import torch

from . import __version__, tissue
from .bands import DEFAULT_BANDS, band_sampling, parse_bands
from .detect import DEFAULT_BOX, indices, rules_detector
from .errors import Parser, check_input_file, check_output_file, check_output_folder
from .io import MAX_MEGAPIXELS
from .optics import DEFAULT_SURFACE, SURFACE_MODELS

SURFACE_HELP = ("skin surface model of eq 3.1.1's diffuse term: thesis (default; rho_d includes the front surface, "
                "as the thesis defines it and its measured images support) or conserving (subsurface part only; "
                "energy-conserving)")


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


def cmd_spectra(args: argparse.Namespace) -> int:
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
        head = f"{'skin':<14}{'mel':>6}{'blood':>6}{'oxy':>6}  " + "".join(
            f"{c:>7g}" for c in cols) + f"{'NDGRI':>9}{'NDSI':>8}  box"
        print(head)
        for k in range(min(len(labels), 50)):
            print(f"{labels[k]:<14}{pdict['melanosome'][k]:>6.3f}{pdict['blood'][k]:>6.2f}"
                  f"{pdict['oxygenation'][k]:>6.2f}  " + "".join(f"{x:>7.3f}" for x in vals[k].tolist())
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


# ------------------------------------------------------------------------------------------------- render
def _scene_from_args(args):
    from .render.scene import Atmosphere, Camera, Sun, default_scene

    cam = Camera(width=args.width, height=args.height, zenith_deg=args.camera_zenith,
                 azimuth_deg=args.camera_azimuth, range_m=args.range, fov_deg=args.fov)
    atm = Atmosphere(aerosol_500nm=args.aerosol, precipitable_water_cm=args.water, ozone_atm_cm=args.ozone,
                     pressure_pa=args.pressure, day_of_year=args.day_of_year)
    sun = Sun(zenith_deg=args.source_zenith, azimuth_deg=args.source_azimuth, sky_fraction=args.sky, atmosphere=atm)
    subject = "file" if args.mesh else "anny"
    sc = default_scene(subject=subject, mesh_path=args.mesh, skin=args.skin, camera=cam, sun=sun,
                       panels=args.panels, diffuse_only=args.diffuse_only, ground=not args.no_ground,
                       surface=args.surface, illumination=args.illumination)
    if args.bands:
        sc.bands = [[b.center_nm, b.fwhm_nm] for b in parse_bands(args.bands)]
    if args.sky_background:
        sc.background = "sky"
    return sc


def _check_angle(name, v, lo, hi):
    if not (lo <= v <= hi):  # NaN fails too
        raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}] degrees, got {v:g}")


def _check_number(name, v, lo=-math.inf, hi=math.inf, what="a number"):
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"{name} must be {what} in [{lo:g}, {hi:g}], got {v:g}")


#: the atmosphere options of ``render`` -> ``scene.Atmosphere`` fields
ATMOSPHERE_OPTIONS = {"--aerosol": "aerosol_500nm", "--water": "precipitable_water_cm", "--ozone": "ozone_atm_cm",
                      "--pressure": "pressure_pa", "--day-of-year": "day_of_year"}


def _check_atmosphere(args) -> None:
    """The atmosphere options within ``scene.ATMOSPHERE_RANGES``; a sun above the horizon for "spectrl2"."""
    from .render.light import MODELS
    from .render.scene import ATMOSPHERE_RANGES

    for opt, key in ATMOSPHERE_OPTIONS.items():
        lo, hi = ATMOSPHERE_RANGES[key]
        _check_number(opt, getattr(args, opt[2:].replace("-", "_")), lo, hi)
    if args.illumination not in MODELS:
        raise ValueError(f"--illumination must be one of {', '.join(sorted(MODELS))}, got {args.illumination!r}")
    if args.illumination == "spectrl2" and not args.source_zenith < 90:
        raise ValueError(f"--source-zenith must be below 90 degrees for --illumination spectrl2 (a sun above the "
                         f"horizon), got {args.source_zenith:g}")


#: ``generate --compile`` choices -> ``dataset.generate.generate(compile=...)``
COMPILE_CHOICES: dict[str, bool | str] = {"auto": "auto", "on": True, "off": False}
#: the largest --sample (the frame cap, MAX_MEGAPIXELS, is io's: render, experiment, detect and calibrate share it)
MAX_SAMPLE = 10_000_000


def _check_frame(args, bands: int, suns: int = 1) -> None:
    """Resolution within the cap and an estimate of the memory the frame needs within what the machine has."""
    import os

    _check_number("--max-megapixels", args.max_megapixels, 1e-6, 1e6, "a positive number")
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


def cmd_render(args: argparse.Namespace) -> int:
    from .devices import check_device
    from .render.outputs import elm_warning, write_outputs
    from .render.pipeline import render
    from .render.sensor import Sensor

    check_output_folder(args.out, "--out")
    _check_angle("--source-zenith", args.source_zenith, 0, 90)
    _check_angle("--camera-zenith", args.camera_zenith, 0, 180)
    _check_number("--source-azimuth", args.source_azimuth, -360, 360)
    _check_number("--camera-azimuth", args.camera_azimuth, -360, 360)
    _check_number("--sky", args.sky, 0, 1)
    _check_atmosphere(args)
    _check_number("--range", args.range, 0.1, 1e5, "a distance in m")
    _check_number("--fov", args.fov, 0.01, 179, "an angle in degrees")
    if args.mesh:
        check_input_file(args.mesh, "--mesh", (".obj", ".ply"))
    _check_frame(args, len(parse_bands(args.bands)) if args.bands else len(DEFAULT_BANDS))
    device = check_device(args.device)
    sc = _scene_from_args(args)
    path: dict[str, Any] = {}
    if args.illumination == "spectrl2":  # the sensor's path through the light model's atmosphere
        from .render.light import path_terms
        from .render.pipeline import scene_light

        path = path_terms(sc.suns[0].atmosphere, scene_light(sc, torch.float64).sky[0].tolist(), sc.bands, args.range)
    sensor = Sensor(noise=not args.no_noise, seed=args.seed, **path)
    res = render(sc, device=device, sensor=sensor, elm=args.elm, compile=args.compile)
    info = write_outputs(res, sc.to_dict(), args.out, sensor=sensor)
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


def cmd_experiment(args: argparse.Namespace) -> int:
    from . import experiment
    from .devices import check_device
    from .render.sensor import Sensor

    check_output_folder(args.out, "--out")
    _check_frame(args, 4, len(experiment.ANGLES_DEG) * len(experiment.MODELS))
    device = check_device(args.device)
    res = experiment.run(args.out, width=args.width, height=args.height, sensor=Sensor(noise=not args.no_noise),
                         device=device, panels=args.panels, surface=args.surface)
    if args.json:
        print(json.dumps({k: v for k, v in res.items() if k != "surface_energy"}))
    else:
        for k, a in enumerate(res["angles_deg"]):
            print(f"source {a:4.0f}°: sunlit skin inside the box: diffuse-only {res['detected_fraction_diffuse'][k]:.3f},"
                  f" thesis {res['detected_fraction_thesis'][k]:.3f}, conserving "
                  f"{res['detected_fraction_conserving'][k]:.3f}; Bhattacharyya (diffuse vs {res['surface']}) "
                  f"{res['bhattacharyya'][k]:.3f}")
        if "lambertian_panel_error" in res:
            plain = res[f"detected_fraction_{res['surface']}_lambertian_elm"]
            for k, a in enumerate(res["angles_deg"]):
                errs = ", ".join(f"{100 * e:.1f}%" for e in res["lambertian_panel_error"][k])
                print(f"source {a:4.0f}°: skin reflectance error if the panels are taken as Lambertian: {errs}; "
                      f"{res['surface']} model inside the box with plain ELM {plain[k]:.3f}")
        print(f"Appendix C middle panel: {res['appendix_c_middle_reflectance']:.4f} (true 0.40); wrote {args.out}")
    return 0


# ---------------------------------------------------------------------------------------------------- fits
def cmd_fit_skin(args: argparse.Namespace) -> int:
    from . import fit

    check_output_file(args.out, "--out", (".csv",))
    if args.plot:
        check_output_folder(args.plot, "--plot")
    _check_number("--r0", args.r0, 0, 0.5, "a front-surface reflectance")
    if args.noise is not None:
        _check_number("--noise", args.noise, 1e-9, 1, "a reflectance standard deviation")
    names, R, wl = fit.read_spectra_csv(check_input_file(args.spectra, "SPECTRA", (".csv",)))
    res = fit.fit_skin(R, wl, r0=args.r0, noise=args.noise)
    fit.write_params_csv(args.out, names, res)
    if args.plot:
        from pathlib import Path

        from .plots import fit_spectra

        Path(args.plot).mkdir(parents=True, exist_ok=True)
        fit_spectra(Path(args.plot) / "fits.png", names, wl, R, res.fitted, res.rmse)
    if args.json:
        print(json.dumps({"rmse": res.rmse.tolist(), "converged": res.converged.tolist(), "seconds": res.seconds,
                          "params": res.reported()}))
    else:
        print(f"fitted {len(names)} spectra in {res.seconds:.2f} s: RMSE median {float(res.rmse.median()):.4f}, "
              f"max {float(res.rmse.max()):.4f}; converged {int(res.converged.sum())}/{len(names)}; "
              f"wrote {args.out}")
        und = [k for j, k in enumerate(fit.NAMES) if not bool(res.identifiable[:, j].any())]
        if und:
            print(f"not determined by these data (left empty): {', '.join(und)}")
    return 0


def cmd_fit_brdf(args: argparse.Namespace) -> int:
    from . import fit
    from .io import write_text
    from .optics import cosines_from_angles, rho0_to_n

    check_output_file(args.out, "--out", (".json",))
    if args.plot:
        check_output_file(args.plot, "--plot", (".png",))
    (ti, tr, dp), f, bands = fit.read_brdf_csv(check_input_file(args.data, "DATA", (".csv",)))
    res = fit.fit_brdf(ti, tr, dp, f, diffuse=not args.no_diffuse)
    doc = {"bands_nm": bands, "sigma2": res.sigma2.tolist(), "rho0": res.rho0.tolist(),
           "n": rho0_to_n(res.rho0).tolist(), "rho_d": res.rho_d.tolist(), "rmse": res.rmse.tolist(),
           "converged": res.converged.tolist()}
    write_text(args.out, json.dumps(doc, indent=1))
    if args.plot:
        from .plots import fit_brdf_curves

        def model(a, b, c):
            ci, cr, c2b = (x[:, None] for x in cosines_from_angles(a, b, c))
            return fit.brdf_model(ci, cr, c2b, res.sigma2, res.rho0, None if args.no_diffuse else res.rho_d)

        fit_brdf_curves(args.plot, ti, tr, dp, f, model, bands)
    if args.json:
        print(json.dumps(doc))
    else:
        for k, b in enumerate(bands):
            print(f"{b:g} nm: sigma2 {doc['sigma2'][k]:.4f}, rho0 {doc['rho0'][k]:.4f} (n {doc['n'][k]:.3f}), "
                  f"rho_d {doc['rho_d'][k]:.3f}, RMSE {doc['rmse'][k]:.3g} sr^-1")
    return 0


# ------------------------------------------------------------------------------------------------ datasets
def cmd_generate(args: argparse.Namespace) -> int:
    from .dataset.config import load_config
    from .dataset.generate import generate
    from .devices import check_device

    if args.resume and args.overwrite:
        raise ValueError("--resume and --overwrite exclude each other")
    check_output_folder(args.out, "--out")
    if args.config:
        check_input_file(args.config, "--config", (".toml",))
    cfg = load_config(args.config)
    if args.surface:
        cfg["skin"]["surface"] = args.surface  # one of SURFACE_MODELS (argparse choices)
    for p in cfg["subject"]["meshes"]:
        check_input_file(p, "subject.meshes", (".obj", ".ply"))
    if args.backend == "local":
        check_device(args.device)
    if args.seed < 0:
        raise ValueError(f"--seed must be a non-negative integer, got {args.seed}")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    man = generate(cfg, args.configs, args.seed, args.out, resume=args.resume, overwrite=args.overwrite,
                   quiet=args.quiet or args.json, device=args.device, backend=args.backend, address=args.address,
                   workers=args.workers, images=args.images, compile=COMPILE_CHOICES[args.compile])
    rows = sum(s["rows"] for s in man["shards"])
    if args.json:
        print(json.dumps({"out": str(args.out), "configs": man["configs"], "groups": man["groups"],
                          "shards": len(man["shards"]), "rows": rows}))
    else:  # --quiet hides the progress bar, not the result
        print(f"wrote {len(man['shards'])} shards, {rows} rows ({man['groups']} pose groups) to {args.out}")
    return 0


def cmd_dataset_verify(args: argparse.Namespace) -> int:
    from .dataset.generate import verify, verify_line, verify_summary

    rep = verify(args.dir)
    if args.json:
        print(json.dumps(verify_summary(rep)))
    else:
        print(verify_line(rep))
    return 0 if rep["ok"] else 1


# ------------------------------------------------------------------------------------------------ boundaries
def cmd_train(args: argparse.Namespace) -> int:
    from . import boundaries as Bd

    check_output_file(args.out, "--out", (".pt",))
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1 (0 would write an untrained model), got {args.steps}")
    _check_number("--pfa-budget", args.pfa_budget, 0, 0.999, "a false-alarm probability")
    _check_number("--scene-budget", args.scene_budget, 0, 0.999, "a false-alarm probability")
    if args.method == "classifier":
        return _train_classifier(args)
    X, Y = Bd.load_skin_rows(args.data, sunlit_only=args.sunlit_only)
    scene = None if args.no_scene else Bd.load_scene_rows(args.data)
    opts = {"hidden": args.hidden, "steps": args.steps, "seed": args.seed}
    domain = Bd.domain_from_manifest(args.data)
    if args.method == "quantiles":
        opts["q"] = args.q
    else:
        opts.update(margin=args.margin, width_cost=args.width_cost, spread_cost=args.spread_cost)
    model, info = Bd.learn(X, Y, args.method, args.pfa_budget, domain=domain,
                           ndvn_quantile=None if args.no_ndvn_rule else Bd.NDVN_QUANTILE, scene=scene,
                           scene_budget=args.scene_budget, **opts)
    info["options"].pop("domain", None)
    info["light_classes"] = ["sunlit"] if args.sunlit_only else ["sunlit", "shadow"]
    scene_text = "" if scene is None else (f"; scene non-skin {info['pfa_scene_train']:.2e} <= {args.scene_budget:g} "
                                           f"of {info['scene_pixels']} training pixels")
    return _save_trained(args, Bd.save, model, info, (
        f"trained ({args.method}) on {info['rows']} {'sunlit ' if args.sunlit_only else ''}skin pixels, loss "
        f"{info['loss']:.5f}; NDVN rule d1 {info['ndvn_min']:.3f}; false-alarm scale {info['scale']:.3f}: worst Pfa "
        f"{info['pfa_train_worst']:.2e} <= {args.pfa_budget:g} on the earthlib train partition over "
        f"{info['calibration_configs']} configurations{scene_text}"))


def _save_trained(args, save, model, info: dict, text: str) -> int:
    """Record the training data in the summary, write the checkpoint, report."""
    from .dataset.files import dataset_surface, manifest_sha256

    info.update(training_manifest_sha256=manifest_sha256(args.data), data=str(args.data),
                surface=dataset_surface(args.data))
    save(model, args.out, info)
    print(json.dumps({**info, "out": str(args.out)}) if args.json else f"{text}; wrote {args.out}")
    return 0


def _train_classifier(args) -> int:
    from . import boundaries as Bd
    from . import classifier as Cl

    X, R, label, sunlit = Cl.load_rows(args.data)
    model, info = Cl.train_classifier(X, R, label, sunlit, hidden=max(args.hidden, 1), steps=args.steps,
                                      seed=args.seed, domain=Bd.domain_from_manifest(args.data),
                                      pfa_budget=args.pfa_budget,
                                      scene_budget=None if args.no_scene else args.scene_budget,
                                      sunlit_only=args.sunlit_only)
    return _save_trained(args, Cl.save, model, info, (
        f"trained (classifier) on {info['rows']} {'sunlit ' if args.sunlit_only else ''}skin pixels; threshold "
        f"{info['threshold']:.3f} (logit) for Pfa <= {args.pfa_budget:g} on the earthlib train partition over "
        f"{info['calibration_configs']} configurations; training skin kept {info['train_coverage']:.3f}, scene "
        f"non-skin {info['pfa_scene_train']:.2e}"))


def _checkpoint(path, what: str):
    """(model, training summary) of a boundary or classifier checkpoint; one-line errors for bad files."""
    from pathlib import Path

    from .evaluate import load_model

    check_input_file(path, what)  # missing, a folder or unreadable: says which
    model, ck = load_model(path, what)
    return model, {**ck.get("meta", {}), "checkpoint": Path(path).name}


def cmd_export(args: argparse.Namespace) -> int:
    from .classifier import SkinClassifier
    from .export import export, write_model_cards

    check_output_folder(args.out, "--out")
    if args.metrics:
        check_input_file(args.metrics, "--metrics", (".json",))
    model, train = _checkpoint(args.model, "--model")
    if isinstance(model, SkinClassifier):
        raise ValueError(f"--model {args.model!r} is a classifier; boundaries.onnx needs a box model (pass the "
                         "classifier as --detector)")
    trains = {"boundaries": train}
    baseline = None
    if args.baseline:
        baseline, trains["baseline_box"] = _checkpoint(args.baseline, "--baseline")
        if isinstance(baseline, SkinClassifier):
            raise ValueError(f"--baseline {args.baseline!r} must be a box model (torchskin train --hidden 0)")
    detector, trains["detector"] = (model, train) if not args.detector else _checkpoint(args.detector, "--detector")
    evaluation = None
    if args.metrics:
        try:
            with open(args.metrics) as fh:
                evaluation = json.load(fh)
        except (OSError, ValueError) as e:
            raise ValueError(f"cannot read --metrics {args.metrics!r}: {e}") from None
        if not isinstance(evaluation, dict) or not {"learned", "static"} <= set(evaluation):
            raise ValueError(f"--metrics {args.metrics!r} is not a torchskin evaluate --save result")
    reason = args.detector_reason or ("the configuration-dependent boxes of --model" if not args.detector else "")
    from .evaluate import MIN_REFLECTANCE

    floor = (evaluation or {}).get("min_reflectance", MIN_REFLECTANCE)
    det_meta = {"detector_model": trains["detector"]["checkpoint"], "detector_reason": reason,
                "checkpoint": trains["detector"]["checkpoint"], "min_reflectance": f"{float(floor):g}"}
    paths = export(model, args.out, train.get("training_manifest_sha256", ""), surface=train.get("surface", ""),
                   baseline=baseline, detector=detector, detector_meta=det_meta, checkpoints={
                       k: v["checkpoint"] for k, v in trains.items()})
    paths.update(write_model_cards(args.out, train, evaluation, trains))
    print(json.dumps(paths) if args.json else "wrote " + ", ".join(paths.values()))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .dataset.files import manifest_sha256
    from .evaluate import boxes_plot, compare_plot, evaluate, plots, table
    from .io import write_text

    if args.plots:
        check_output_folder(args.plots, "--plots")
    if args.save:
        check_output_file(args.save, "--save", (".json",))
    res = evaluate(args.data, args.model)
    res["data"] = str(args.data)
    res["data_manifest_sha256"] = manifest_sha256(args.data)
    res["model"] = str(args.model[0])
    if args.plots:
        plots(res, args.plots)
        compare_plot(res, Path(args.plots) / "comparison.png")
        first = res["models"][0]
        if first["kind"] == "boxes":
            boxes_plot(args.data, first["path"], Path(args.plots) / "boxes.png")
    if args.save:
        write_text(args.save, json.dumps(res, indent=1))
    if args.json:
        print(json.dumps({k: res[k] for k in ("models", "learned", "static", "bins", "sun_zenith_ge_60")}))
    else:
        print(table(res))
    return 0


# -------------------------------------------------------------------------------------------------- bench
def cmd_bench(args: argparse.Namespace) -> int:
    from . import bench

    if args.only is not None and not [x for x in args.only.split(",") if x.strip()]:
        raise ValueError("--only needs benchmark names, e.g. --only render,materials")
    only = [x.strip() for x in args.only.split(",") if x.strip()] if args.only else None
    res = bench.run(only, compile=args.compile)
    if args.json:
        print(json.dumps(res))
    else:  # each benchmark's figures, numbers only (--json has everything)
        for name, r in res.items():
            figures = [f"{k} {v:.4g}" for k, v in r.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
            print(f"{name:<14}" + ", ".join(figures))
    return 0


def cmd_light(args: argparse.Namespace) -> int:
    """Per sun zenith: the light model's diffuse / direct horizontal irradiance per band, and the direct beam's
    first-band / last-band ratio (how red the low sun is)."""
    from .render.light import light_tables
    from .render.scene import Atmosphere, Sun

    _check_atmosphere(argparse.Namespace(**{**vars(args), "source_zenith": 0.0}))
    try:
        zeniths = [float(z) for z in args.zenith.split(",")]
    except ValueError:
        raise ValueError(f"--zenith must be comma-separated degrees, got {args.zenith!r}") from None
    _check_number("--sky", args.sky, 0, 1)
    for z in zeniths:
        _check_angle("--zenith", z, 0, 90)
        if not z < 90:  # no direct light on a horizontal surface: the ratio is undefined
            raise ValueError(f"--zenith must be below 90 degrees (a sun above the horizon), got {z:g}")
    bands = parse_bands(args.bands) if args.bands else DEFAULT_BANDS
    atm = Atmosphere(aerosol_500nm=args.aerosol, precipitable_water_cm=args.water, ozone_atm_cm=args.ozone,
                     pressure_pa=args.pressure, day_of_year=args.day_of_year)
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


def add_light_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin light`` command."""
    lp = sub.add_parser("light", help="the light model's direct and diffuse irradiance per band and sun zenith",
                        description="Tabulate a light model (render.light): diffuse over direct horizontal "
                                    "irradiance per band, and the direct beam's colour, per sun zenith.")
    lp.add_argument("--zenith", default="10,45,60,75,85", help="sun zeniths, degrees (default 10,45,60,75,85)")
    lp.add_argument("--bands", metavar="C[/FWHM],...", help="bands in nm (default 544,633,1080,1580)")
    lp.add_argument("--illumination", default="spectrl2", metavar="MODEL", help="light model (default spectrl2)")
    _atmosphere_options(lp)
    lp.add_argument("--sky", type=float, default=0.1, help="thesis: sky irradiance / sun irradiance (default 0.1)")
    lp.add_argument("--json", action="store_true", help="print one JSON object")
    lp.set_defaults(func=cmd_light)


def _atmosphere_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--aerosol", type=float, default=0.1, help="spectrl2: aerosol optical depth at 500 nm (0.1)")
    p.add_argument("--water", type=float, default=1.42, help="spectrl2: precipitable water, cm (default 1.42)")
    p.add_argument("--ozone", type=float, default=0.344, help="spectrl2: ozone column, atm-cm (default 0.344)")
    p.add_argument("--pressure", type=float, default=101325.0, help="spectrl2: surface pressure, Pa (101325)")
    p.add_argument("--day-of-year", type=int, default=172, help="spectrl2: day of year, 1-366 (default 172)")


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="torchskin", description="Physics-based multispectral skin toolkit. Errors "
                                 "print one line (status 2: bad input; 1: a failure); --debug (anywhere on the "
                                 "command line) shows the traceback instead.")
    ap.add_argument("--version", action="version", version=f"torchskin {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=Parser)
    add_spectra_command(sub)
    add_render_command(sub)
    add_light_command(sub)
    add_experiment_command(sub)
    add_fit_skin_command(sub)
    add_fit_brdf_command(sub)
    add_generate_command(sub)
    add_dataset_command(sub)
    add_train_command(sub)
    add_export_command(sub)
    add_evaluate_command(sub)
    add_onboard_command(sub)
    add_bench_command(sub)
    return ap


def add_spectra_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin spectra`` command."""
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


def add_render_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin render`` command."""
    rp = sub.add_parser("render", help="render a calibrated multispectral frame of a subject with panels",
                        description="Ray-cast a subject between two reference panels under a sun, through the "
                                    "sensor chain, calibrate with ELM and run the rules detector.")
    rp.add_argument("--out", required=True, help="output folder")
    src = rp.add_mutually_exclusive_group()
    src.add_argument("--mesh", metavar="PATH", help="OBJ/PLY subject (all skin)")
    src.add_argument("--subject", choices=["anny"], default="anny", help="parametric anny body (default)")
    rp.add_argument("--skin", default="I-II", help=f"skin preset ({', '.join(tissue.PRESETS)})")
    rp.add_argument("--source-zenith", type=float, default=45.0, help="sun zenith, degrees (default 45)")
    rp.add_argument("--source-azimuth", type=float, default=20.0, help="sun azimuth from +x, degrees (default 20)")
    rp.add_argument("--illumination", default="spectrl2", metavar="MODEL",
                    help="light model (render.light): spectrl2 (default: clear-sky sun, sky and ground-reflected "
                         "light from the atmosphere below, via pvlib) or thesis (a 5950 K blackbody sun and a grey "
                         "sky of --sky)")
    _atmosphere_options(rp)
    rp.add_argument("--sky", type=float, default=0.1,
                    help="thesis: sky irradiance / sun irradiance (default 0.1; spectrl2 computes its sky)")
    rp.add_argument("--sky-background", action="store_true",
                    help="rays that hit nothing above the horizon see the isotropic sky (radiance E_sky / pi) "
                         "instead of a black void")
    rp.add_argument("--camera-zenith", type=float, default=90.0, help="camera zenith, degrees (default 90)")
    rp.add_argument("--camera-azimuth", type=float, default=0.0, help="camera azimuth, degrees (default 0)")
    rp.add_argument("--range", type=float, default=9.449, help="camera range, m (default 9.449 = 31 ft)")
    rp.add_argument("--fov", type=float, default=14.0, help="horizontal field of view, degrees (default 14)")
    rp.add_argument("--width", type=int, default=512, help="frame width in pixels (default 512)")
    rp.add_argument("--height", type=int, default=512, help="frame height in pixels (default 512)")
    rp.add_argument("--max-megapixels", type=float, default=MAX_MEGAPIXELS,
                    help=f"refuse frames larger than this (default {MAX_MEGAPIXELS:g}; memory is checked too)")
    rp.add_argument("--bands", metavar="C[/FWHM],...", help="bands in nm (default 544,633,1080,1580)")
    rp.add_argument("--panels", choices=["lambertian", "spectralon", "spectralon-brdf"], default="lambertian",
                    help="reference panels: Lambertian 0.97/0.03 (default), Spectralon Table 3 DHR, or with its BRDF")
    rp.add_argument("--elm", choices=["dhr", "brdf"], default="dhr",
                    help="calibrate with the panels' DHR (ELM) or their BRDF at the geometry (BRDF-ELM)")
    rp.add_argument("--no-noise", action="store_true", help="switch sensor noise off")
    rp.add_argument("--diffuse-only", action="store_true", help="skin as the diffuse model (no specular lobe)")
    rp.add_argument("--surface", choices=SURFACE_MODELS, default=DEFAULT_SURFACE, help=SURFACE_HELP)
    rp.add_argument("--no-ground", action="store_true", help="no ground plane")
    rp.add_argument("--device", default="cpu", help="torch device for shading (cpu, cuda, mps)")
    rp.add_argument("--seed", type=int, default=0, help="noise seed")
    rp.add_argument("--compile", action="store_true",
                    help="run the per-pixel stages as compiled kernels (torch.compile: seconds to compile, for "
                         "repeated renders; the same frame within 1e-5)")
    rp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    rp.set_defaults(func=cmd_render)


def add_experiment_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin experiment`` command."""
    ep = sub.add_parser("experiment", help="the thesis experiment: source 10-85 deg off normal, every skin model",
                        description="The thesis experiment (section 3.4): a Type I/II subject facing the camera at "
                                    "9.449 m, a source 10, 30, 60 and 85 deg off normal; the diffuse-only skin and "
                                    "eq 3.1.1 under both skin surface models, side by side (scatter plots, 2-D "
                                    "histograms, detected fraction against angle, Bhattacharyya coefficients), and "
                                    "Appendix C.")
    ep.add_argument("--out", required=True, help="output folder for figures and experiment.json")
    ep.add_argument("--width", type=int, default=512, help="image width in pixels (default 512)")
    ep.add_argument("--height", type=int, default=512, help="image height in pixels (default 512)")
    ep.add_argument("--max-megapixels", type=float, default=MAX_MEGAPIXELS,
                    help=f"refuse frames larger than this (default {MAX_MEGAPIXELS:g}; memory is checked too)")
    ep.add_argument("--surface", choices=SURFACE_MODELS, default=DEFAULT_SURFACE,
                    help="the combined model reported as detected_fraction_combined (both are always rendered); "
                         + SURFACE_HELP)
    ep.add_argument("--no-noise", action="store_true", help="switch sensor noise off")
    ep.add_argument("--panels", choices=["lambertian", "spectralon", "spectralon-brdf"], default="lambertian",
                    help="reference panels; spectralon-brdf calibrates with BRDF-ELM and reports the error of "
                         "assuming Lambertian panels")
    ep.add_argument("--device", default="cpu", help="torch device for shading (cpu, cuda, cuda:N, mps; default cpu)")
    ep.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    ep.set_defaults(func=cmd_experiment)


def add_fit_skin_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin fit-skin`` command."""
    fp = sub.add_parser("fit-skin", help="fit the skin parameters to measured reflectance spectra",
                        description="Fit the six skin parameters to reflectance spectra (CSV) by minimising the RMSE of "
                                    "eq 2.4.14; parameters the data cannot determine are left empty.")
    fp.add_argument("spectra", help="CSV: header row of wavelengths (nm), one spectrum per row")
    fp.add_argument("--out", required=True, help="output CSV of fitted parameters")
    fp.add_argument("--r0", type=float, default=0.04, help="front-surface reflectance of the measurement")
    fp.add_argument("--noise", type=float, default=None, help="measurement noise for the uncertainties")
    fp.add_argument("--plot", metavar="DIR", help="write measured vs fitted spectra (fits.png) here")
    fp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    fp.set_defaults(func=cmd_fit_skin)


def add_fit_brdf_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin fit-brdf`` command."""
    bf = sub.add_parser("fit-brdf", help="fit microfacet sigma2 and rho0 per band to goniometric data",
                        description="Fit the Gaussian microfacet lobe (sigma2, rho0) and a diffuse reflectance per band "
                                    "to goniometric BRDF samples (CSV).")
    bf.add_argument("data", help="CSV: theta_i_deg,theta_r_deg,delta_phi_deg,<band nm>,... (BRDF in 1/sr)")
    bf.add_argument("--out", required=True, help="output JSON of fitted parameters")
    bf.add_argument("--no-diffuse", action="store_true", help="fit the lobe alone (no diffuse term)")
    bf.add_argument("--plot", metavar="PNG", help="measured and fitted in-plane curves (Fig 21 style)")
    bf.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    bf.set_defaults(func=cmd_fit_brdf)


def add_generate_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin generate`` command."""
    gp = sub.add_parser("generate", help="generate a randomized labelled pixel dataset (Parquet shards)",
                        description="Draw random sun/camera/subject/skin configurations (TOML config, see "
                                    "torchskin/dataset/config.py), render them and write balanced labelled skin / "
                                    "non-skin pixels as Parquet shards with a checksummed manifest.")
    gp.add_argument("--config", metavar="TOML", help="configuration (default: the built-in one)")
    gp.add_argument("--configs", type=int, default=100, help="number of configurations (default 100)")
    gp.add_argument("--surface", choices=SURFACE_MODELS,
                    help="skin surface model, overriding the config's skin.surface (default there: thesis); "
                         + SURFACE_HELP)
    gp.add_argument("--seed", type=int, default=0, help="master seed (default 0)")
    gp.add_argument("--out", required=True, help="output folder")
    gp.add_argument("--resume", action="store_true", help="keep valid shards of an earlier run, redo the rest")
    gp.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    gp.add_argument("--quiet", action="store_true", help="no progress bar (the one-line summary is still printed)")
    gp.add_argument("--device", default="cpu", help="torch device for shading (cpu, cuda, cuda:N, mps; default cpu)")
    gp.add_argument("--images", action="store_true", help="also store full reflectance cubes (images-*.npy)")
    gp.add_argument("--compile", choices=list(COMPILE_CHOICES), default="auto",
                    help="render with the compiled kernels (torch.compile; seconds to compile, then faster): on, "
                         "off, or auto (default: on from 20,000 configurations when a C++ compiler is present)")
    gp.add_argument("--backend", choices=["local", "ray"], default="local", help="run shards here or on Ray")
    gp.add_argument("--address", help="Ray cluster address (default: start a local cluster)")
    gp.add_argument("--workers", type=int, help="CPUs of the local Ray cluster (default: all)")
    gp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    gp.set_defaults(func=cmd_generate)


def add_dataset_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin dataset`` command."""
    dp = sub.add_parser("dataset", help="dataset utilities", description="Dataset utilities: verify.")
    dsub = dp.add_subparsers(dest="dataset_command", required=True)
    vp = dsub.add_parser("verify", help="check shards against the manifest (non-zero exit on problems)")
    vp.add_argument("dir")
    vp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    vp.set_defaults(func=cmd_dataset_verify)


def add_train_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin train`` command."""
    tp = sub.add_parser("train", help="learn configuration-dependent boundaries from a generated dataset",
                        description="Learn configuration-dependent rules boxes (or a classifier) from a generated "
                                    "dataset, tuned to a false-alarm budget on the earthlib train spectra.")
    tp.add_argument("--data", required=True, help="dataset folder (torchskin generate)")
    tp.add_argument("--out", required=True, help="checkpoint (.pt)")
    tp.add_argument("--method", choices=("boxes", "quantiles", "classifier"), default="boxes",
                    help="boxes: most sunlit skin per configuration with the earthlib train spectra kept a margin "
                         "outside (default); quantiles: conditional quantiles of NDGRI and NDSI (pinball loss); "
                         "classifier: a configuration-conditioned MLP on scale-invariant band ratios "
                         "(torchskin.classifier), thresholded at the false-alarm budget")
    tp.add_argument("--margin", type=float, default=0.03,
                    help="boxes: distance (index units) kept from every earthlib train spectrum (default 0.03)")
    tp.add_argument("--width-cost", type=float, default=0.05,
                    help="boxes: cost per unit of box width, keeps the box tight (default 0.05)")
    tp.add_argument("--spread-cost", type=float, default=0.1,
                    help="boxes: cost of the boxes' spread over configurations (squared distance to their mean): "
                         "the box moves with the configuration only where the data pay for it (default 0.1)")
    tp.add_argument("--q", type=float, default=0.15, help="quantiles: quantile of the box edges (default 0.15)")
    tp.add_argument("--no-ndvn-rule", action="store_true",
                    help="boxes and quantiles: no visible/NIR rule (NDVN >= d1, d1 just below the training skin's "
                         "NDVN): the thesis's two indices alone")
    tp.add_argument("--steps", type=int, default=1500, help="optimisation steps (default 1500)")
    tp.add_argument("--hidden", type=int, default=32, help="MLP width (0: one constant box; default 32)")
    tp.add_argument("--seed", type=int, default=0, help="seed of the initial weights and batches (default 0)")
    tp.add_argument("--pfa-budget", type=float, default=1e-3,
                    help="false-alarm budget on the earthlib train partition (default 1e-3)")
    tp.add_argument("--scene-budget", type=float, default=1e-4,
                    help="the largest share of the training dataset's own non-skin pixels "
                         "(clothing, ground and confusers, sunlit and shadowed) the boxes may call skin, held in "
                         "training and tuning (default 1e-4)")
    tp.add_argument("--no-scene", action="store_true",
                    help="hold only the earthlib spectra to a budget, not the dataset's non-skin pixels")
    tp.add_argument("--sunlit-only", action="store_true",
                    help="learn from sunlit skin only (default: sunlit and shadowed skin)")
    tp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    tp.set_defaults(func=cmd_train)


def add_export_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin export`` command."""
    xp = sub.add_parser("export", help="export a boundary checkpoint to boundaries.onnx and detector.onnx",
                        description="Export checkpoints to ONNX (boundaries.onnx, baseline_box.onnx, detector.onnx) with "
                                    "metadata and model cards.")
    xp.add_argument("--model", required=True, help="checkpoint (.pt) from torchskin train")
    xp.add_argument("--out", required=True, help="output folder (e.g. exports/)")
    xp.add_argument("--baseline", metavar="PT", help="a single-box checkpoint (train --hidden 0) exported as "
                                                     "baseline_box.onnx, same inputs and outputs as boundaries.onnx")
    xp.add_argument("--detector", metavar="PT", help="the checkpoint detector.onnx is made from: a box model or a "
                                                     "classifier (default: --model)")
    xp.add_argument("--detector-reason", metavar="TEXT", help="why that model: recorded in detector.onnx's "
                                                              "metadata and model card")
    xp.add_argument("--metrics", metavar="EVAL.json", help="torchskin evaluate --save output for the model cards")
    xp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    xp.set_defaults(func=cmd_export)


def add_evaluate_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin evaluate`` command."""
    ev = sub.add_parser("evaluate", help="Pd / Pfa of learned boundaries vs the static box on held-out data",
                        description="Compare models (checkpoints or ONNX exports) with the static thesis box on a "
                                    "held-out dataset: Pd by skin category, Pfa, decision-region areas; one table.")
    ev.add_argument("--data", required=True, help="held-out dataset folder")
    ev.add_argument("--model", required=True, action="append",
                    help="a model to evaluate (repeatable; one table row each, the static thesis box always last): "
                         "a checkpoint (.pt: boxes or classifier), boundaries.onnx / baseline_box.onnx or "
                         "detector.onnx")
    ev.add_argument("--plots", metavar="DIR", help="write roc.png, pd_heatmap.png and boxes.png here")
    ev.add_argument("--save", metavar="FILE", help="write the full result (JSON, with ROC points) here")
    ev.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    ev.set_defaults(func=cmd_evaluate)


def add_onboard_command(sub: argparse._SubParsersAction) -> None:
    """The onboard commands' entries (they run in the torch-free runtime, ``torchskin.onboard_cli``)."""
    sub.add_parser("detect", help="skin mask of a cube with detector.onnx (numpy + onnxruntime only; "
                                  "see torchskin detect --help)",
                   description="Run by the torch-free onboard runtime: torchskin detect --help.")
    sub.add_parser("calibrate", help="signals to reflectance with ELM through panel regions (numpy only; "
                                     "see torchskin calibrate --help)",
                   description="Run by the torch-free onboard runtime: torchskin calibrate --help.")


def add_bench_command(sub: argparse._SubParsersAction) -> None:
    """The ``torchskin bench`` command."""
    bp = sub.add_parser("bench", help="benchmarks (JSON with --json)",
                        description="Throughput benchmarks: km, render, fit, dataset, detector_onnx, materials.")
    bp.add_argument("--json", action="store_true", help="print one JSON object (no progress output)")
    bp.add_argument("--only", metavar="NAMES", help="comma-separated benchmark names (default: all)")
    bp.add_argument("--compile", action="store_true",
                    help="km: also measure the compiled skin model (slow start); render and dataset always time "
                         "the eager and the compiled kernels side by side")
    bp.set_defaults(func=cmd_bench)


def main(argv: list[str] | None = None) -> int:
    """Parse and run one command; errors propagate to ``torchskin.cli.main`` (``errors.run_command``)."""
    ap = build_parser()
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
