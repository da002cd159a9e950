#!/usr/bin/env python
"""Pipeline step 2/5: learn the detectors compared in step 3 from WORK/train.

    python scripts/pipeline_train.py [--work out/pipeline] [--steps 1000]

Writes WORK/boundaries.trained.pt (configuration-dependent coverage boxes of sunlit and shadowed skin with a
learned visible/NIR rule, earthlib train spectra kept 0.03 outside at Pfa <= 1e-3 and the dataset's own non-skin
pixels at <= 1e-4: `torchskin train` defaults), WORK/baseline_box.trained.pt (the same training with one box for
every configuration: --hidden 0) and WORK/classifier.trained.pt (a configuration-conditioned MLP on band
ratios, thresholded at the same budgets); step 3 calibrates them on the held-out set."""

import argparse
import sys

from torchskin.cli import main

#: extra box training options of the shipped models (none: the defaults of `torchskin train`)
BOX_OPTIONS: list[str] = []


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--steps", type=int, default=1000)
    a = ap.parse_args(argv)
    common = ["--data", f"{a.work}/train", "--steps", str(a.steps)]
    for name, extra in (("boundaries", BOX_OPTIONS), ("baseline_box", [*BOX_OPTIONS, "--hidden", "0"]),
                        ("classifier", ["--method", "classifier"])):
        print(f"[train] {name}", flush=True)
        rc = main(["train", *common, "--out", f"{a.work}/{name}.trained.pt", *extra])
        if rc:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(run())
