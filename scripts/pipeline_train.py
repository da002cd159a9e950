#!/usr/bin/env python
"""Pipeline step 2/5: learn the detectors compared in step 3 from WORK/train.

    python scripts/pipeline_train.py [--work out/pipeline] [--steps 1000]

Writes WORK/<name>.trained.pt for each model the registered detector kinds contribute to the pipeline
(``registry.pipeline_runs``: the name and its `torchskin train` arguments, the command's defaults otherwise,
including the false-alarm budgets: earthlib train spectra Pfa <= 1e-3, the dataset's own non-skin pixels
<= 1e-4); step 3 calibrates them on the held-out set. Today: boundaries (configuration-dependent boxes),
baseline_box (one box for every configuration) and classifier (an MLP on band ratios)."""

import argparse
import sys

from torchskin.cli import main
from torchskin.detectors import registry


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--steps", type=int, default=1000)
    a = ap.parse_args(argv)
    common = ["--data", f"{a.work}/train", "--steps", str(a.steps)]
    for r in registry.pipeline_runs():
        print(f"[train] {r.name}", flush=True)
        rc = main(["train", *common, "--out", f"{a.work}/{r.name}.trained.pt", *r.args])
        if rc:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(run())
