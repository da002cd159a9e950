#!/usr/bin/env python
"""Pipeline step 3/5: evaluate WORK/boundaries.pt on WORK/heldout against the static box.

    python scripts/pipeline_evaluate.py [--work out/pipeline]

Writes WORK/evaluation.json (full result) and WORK/plots/{roc,pd_heatmap}.png."""

import argparse
import sys

from torchskin.cli import main


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    a = ap.parse_args(argv)
    print("[evaluate] held-out configurations and earthlib test spectra", flush=True)
    return main(["evaluate", "--data", f"{a.work}/heldout", "--model", f"{a.work}/boundaries.pt",
                 "--plots", f"{a.work}/plots", "--save", f"{a.work}/evaluation.json"])


if __name__ == "__main__":
    sys.exit(run())
