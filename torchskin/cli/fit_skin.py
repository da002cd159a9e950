"""``torchskin fit-skin``: the six skin parameters fitted to measured reflectance spectra (CSV)."""

from __future__ import annotations

import argparse
import json

from ..errors import check_input_file, check_output_file, check_output_folder
from .options import add_json, add_out_file, check_number


def cmd_fit_skin(args: argparse.Namespace) -> int:
    """Run ``torchskin fit-skin`` (``fit.fit_skin``) and write the fitted parameters as CSV."""
    from .. import fit

    check_output_file(args.out, "--out", (".csv",))
    if args.plot:
        check_output_folder(args.plot, "--plot")
    check_number("--r0", args.r0, 0, 0.5, "a front-surface reflectance")
    if args.noise is not None:
        check_number("--noise", args.noise, 1e-9, 1, "a reflectance standard deviation")
    names, R, wl = fit.read_spectra_csv(check_input_file(args.spectra, "SPECTRA", (".csv",)))
    res = fit.fit_skin(R, wl, r0=args.r0, noise=args.noise)
    fit.write_params_csv(args.out, names, res)
    if args.plot:
        from pathlib import Path

        from ..plots import fit_spectra

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


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin fit-skin`` command."""
    fp = sub.add_parser("fit-skin", help="fit the skin parameters to measured reflectance spectra",
                        description="Fit the six skin parameters to reflectance spectra (CSV) by minimising the RMSE of "
                                    "eq 2.4.14; parameters the data cannot determine are left empty.")
    fp.add_argument("spectra", help="CSV: header row of wavelengths (nm), one spectrum per row")
    add_out_file(fp, "the fitted parameters, CSV")
    fp.add_argument("--r0", type=float, default=0.04, help="front-surface reflectance of the measurement")
    fp.add_argument("--noise", type=float, default=None, help="measurement noise for the uncertainties")
    fp.add_argument("--plot", metavar="DIR", help="write measured vs fitted spectra (fits.png) here")
    add_json(fp)
    fp.set_defaults(func=cmd_fit_skin)
    return fp
