"""``torchskin experiment``: the thesis experiment (section 3.4), every skin model side by side."""

from __future__ import annotations

import argparse
import json

from ..errors import check_output_folder
from .options import add_device, add_frame, add_json, add_no_noise, add_out_folder, add_panels, add_surface, check_frame


def cmd_experiment(args: argparse.Namespace) -> int:
    """Run ``torchskin experiment`` (``torchskin.experiment.run``) and summarise it per source angle."""
    from .. import experiment
    from ..devices import check_device
    from ..render.sensor import Sensor

    check_output_folder(args.out, "--out")
    check_frame(args, 4, len(experiment.ANGLES_DEG) * len(experiment.MODELS))
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


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin experiment`` command."""
    ep = sub.add_parser("experiment", help="the thesis experiment: source 10-85 deg off normal, every skin model",
                        description="The thesis experiment (section 3.4): a Type I/II subject facing the camera at "
                                    "9.449 m, a source 10, 30, 60 and 85 deg off normal; the diffuse-only skin and "
                                    "eq 3.1.1 under both skin surface models, side by side (scatter plots, 2-D "
                                    "histograms, detected fraction against angle, Bhattacharyya coefficients), and "
                                    "Appendix C.")
    add_out_folder(ep, "figures and experiment.json")
    add_frame(ep)
    add_surface(ep, lead="the combined model reported as detected_fraction_combined (both are always rendered)")
    add_no_noise(ep)
    add_panels(ep, note="spectralon-brdf calibrates with BRDF-ELM and reports the error of assuming Lambertian "
                        "panels")
    add_device(ep)
    add_json(ep)
    ep.set_defaults(func=cmd_experiment)
    return ep
