"""``torchskin design-bands``: which bands to buy. The best k bands (k = 1 ... K) for skin detection at the scene
false-alarm budget, per detector range, from datasets rendered once at fine spectral sampling
(``evaluation.band_design``)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import Any

from ..errors import check_output_folder
from .options import add_json, check_number

EPILOG = """example:
  torchskin generate --bands 400:1700:10 --configs 2400 --seed 1 --out fine_train
  torchskin generate --bands 400:1700:10 --configs 960 --seed 2 --config heldout.toml --out fine_heldout
  torchskin generate --bands 400:1700:10 --configs 960 --seed 3 --config heldout.toml --out fine_fresh
  torchskin design-bands --data fine_train --heldout fine_heldout --fresh fine_fresh --out design \\
                         --compare rededge-mx

(heldout.toml: [confusers] and [clothing] partition = "test", as make demo's held-out and test sets.)
Writes design.json, design.md (the table) and design.png (Pd against k per range, the thesis's bands marked)."""


def cmd_design_bands(args: argparse.Namespace) -> int:
    from ..bands import BandSet
    from ..evaluation.band_design import RANGES, design, figure, table
    from ..io import write_text

    ranges = [r.strip() for r in args.ranges.split(",") if r.strip()]
    bad = [r for r in ranges if r not in RANGES]
    if bad or not ranges:
        raise ValueError(f"--ranges must name one or more of {', '.join(RANGES)} (comma-separated), got {args.ranges!r}")
    if not 1 <= args.k_max <= 10:
        raise ValueError(f"--k-max must lie in 1..10, got {args.k_max}")
    check_number("--step", args.step, 1.0, 500.0, "a step in nm")
    check_number("--fwhm", args.fwhm, 0.0, 200.0, "a FWHM in nm (0: monochromatic)")
    check_number("--budget", args.budget, 1e-9, 0.5, "a false-alarm probability")
    check_number("--min-light", args.min_light, 0.0, 2.0, "an irradiance in W m-2 nm-1")
    for name, v, lo in (("--trees", args.trees, 1), ("--kind-trees", args.kind_trees, 0), ("--max-rows", args.max_rows, 100)):
        if v < lo:
            raise ValueError(f"{name} must be at least {lo}, got {v}")
    compare = []
    for spec in args.compare or ():
        name, bands = spec.split("=", 1) if "=" in spec else (spec, spec)  # a path with '=' needs NAME= before it
        name = name.strip()
        if not name or any(c in name for c in "|,\n"):
            raise ValueError(f"--compare {spec!r}: NAME=BANDS with a name of its own (no '|' or ',') is expected")
        compare.append((name, list(BandSet.parse(bands.strip(), option="--compare").bands)))
    if len({n for n, _ in compare}) < len(compare):
        raise ValueError(f"--compare names a camera twice: {[n for n, _ in compare]}")
    out = check_output_folder(args.out, "--out")
    result = design(args.data, args.heldout, args.fresh, ranges, args.k_max, args.step, args.fwhm, args.trees,
                    args.max_rows, args.budget, args.min_light, args.kind_trees or None, compare,
                    progress=not args.quiet)
    for w in result["warnings"]:
        print(f"torchskin design-bands: warning: {w}", file=sys.stderr)
    text = table(result)
    out.mkdir(parents=True, exist_ok=True)
    figure(result, out / "design.tmp.png")  # the figure first: a failure leaves none of the three
    data = json.dumps(_no_nan(result), indent=1)
    write_text(out / "design.json", data)
    write_text(out / "design.md", text)
    os.replace(out / "design.tmp.png", out / "design.png")
    if args.json:
        print(json.dumps(_no_nan(result)))
    else:
        print(text, end="")
        print(f"wrote {out / 'design.json'}, {out / 'design.md'}, {out / 'design.png'}")
    return 0


def _no_nan(x: Any) -> Any:
    """``x`` with every NaN float as None (JSON's null: NaN is not JSON)."""
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, dict):
        return {k: _no_nan(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_no_nan(v) for v in x]
    return x


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin design-bands`` command."""
    p = sub.add_parser(
        "design-bands", help="which bands to buy: a greedy search for k bands per detector range",
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Search greedily (one band added at a time) for the best k bands, k = 1 ... --k-max, for skin "
                    "detection at the scene false-alarm budget, per detector range (silicon 400-1000 nm, InGaAs "
                    "900-1700 nm, both). Candidate bands are synthesised from datasets rendered at fine spectral "
                    "sampling, as detect synthesises a hyperspectral cube. A fast proxy of the lut detector chooses "
                    "on the held-out set. Each chosen set of two or more bands, the thesis's four and each --compare "
                    "camera are then trained as the lut detector, calibrated on the held-out set and judged on the "
                    "fresh set.")
    p.add_argument("--data", required=True, help="training dataset rendered at fine spectral sampling "
                                                 "(e.g. generate --bands 400:1700:10)")
    p.add_argument("--heldout", required=True, help="held-out dataset in the same bands (another seed): the search "
                                                    "and the calibration")
    p.add_argument("--fresh", required=True, help="fresh dataset in the same bands (a third seed): the final scores")
    p.add_argument("--out", required=True, help="output folder: design.json, design.md, design.png")
    p.add_argument("--ranges", default="silicon,ingaas,both",
                   help="detector ranges, comma-separated: silicon (400-1000 nm), ingaas (900-1700 nm), both "
                        "(default all three)")
    p.add_argument("--k-max", type=int, default=6, help="the most bands a set holds (default 6)")
    p.add_argument("--step", type=float, default=20.0, help="candidate band centres every STEP nm (default 20)")
    p.add_argument("--fwhm", type=float, default=20.0, help="candidate bands' FWHM, nm (default 20; 0: monochromatic)")
    p.add_argument("--min-light", type=float, default=0.05,
                   help="leave out candidate bands with less clear-sky light than this, W m-2 nm-1 of global "
                        "horizontal irradiance with the sun at 60 deg in the training data's wettest air (default "
                        "0.05: the water-vapour bands near 1140 and 1340-1480 nm, where a real camera needs 10-100 "
                        "times the exposure; 0 keeps every band)")
    p.add_argument("--budget", type=float, default=1e-4, help="scene false-alarm budget (default 1e-4)")
    p.add_argument("--trees", type=int, default=30, help="the proxy learner's trees (default 30)")
    p.add_argument("--max-rows", type=int, default=60_000, help="rows drawn from each dataset for the search "
                                                                 "(default 60000)")
    p.add_argument("--kind-trees", type=int, default=300,
                   help="the lut detector's trees for the final scores (default 300, as train --method lut); 0 "
                        "skips them (the proxy's scores only; about 20 minutes sooner on 2 cores)")
    p.add_argument("--compare", action="append", metavar="[NAME=]BANDS",
                   help="also score a camera's bands by the same procedure (repeatable): a named camera "
                        "(rededge-mx), a --bands list (NAME=475/32,560/27,...) or a response table (NAME=filters.csv)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_json(p)
    p.set_defaults(func=cmd_design_bands)
    return p
