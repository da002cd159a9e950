"""``torchskin fit-brdf``: the Gaussian microfacet lobe (sigma2, rho0) and a diffuse reflectance per band fitted
to goniometric BRDF samples (CSV)."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from ..errors import check_input_file, check_output_file
from .options import add_json, add_out_file

if TYPE_CHECKING:
    import torch


def cmd_fit_brdf(args: argparse.Namespace) -> int:
    """Run ``torchskin fit-brdf`` (``fit.fit_brdf``) and write the fitted lobe per band as JSON."""
    from .. import fit
    from ..io import write_text
    from ..optics import cosines_from_angles, rho0_to_n

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
        from ..plots import fit_brdf_curves

        def model(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
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


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin fit-brdf`` command."""
    bf = sub.add_parser("fit-brdf", help="fit microfacet sigma2 and rho0 per band to goniometric data",
                        description="Fit the Gaussian microfacet lobe (sigma2, rho0) and a diffuse reflectance per band "
                                    "to goniometric BRDF samples (CSV).")
    bf.add_argument("data", help="CSV: theta_i_deg,theta_r_deg,delta_phi_deg,<band nm>,... (BRDF in 1/sr)")
    add_out_file(bf, "the fitted parameters, JSON")
    bf.add_argument("--no-diffuse", action="store_true", help="fit the lobe alone (no diffuse term)")
    bf.add_argument("--plot", metavar="PNG", help="measured and fitted in-plane curves (Fig 21 style)")
    add_json(bf)
    bf.set_defaults(func=cmd_fit_brdf)
    return bf
