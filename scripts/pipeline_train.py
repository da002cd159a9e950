#!/usr/bin/env python
"""Pipeline step 2/5: learn the configuration-dependent boxes from WORK/train.

    python scripts/pipeline_train.py [--work out/pipeline] [--steps 1000]

Writes WORK/boundaries.pt (coverage boxes, earthlib train spectra kept 0.03 outside, Pfa budget 1e-3)."""

import argparse
import sys

from torchskin.cli import main


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--steps", type=int, default=1000)
    a = ap.parse_args(argv)
    print("[train] learning boundaries", flush=True)
    return main(["train", "--data", f"{a.work}/train", "--out", f"{a.work}/boundaries.pt", "--steps", str(a.steps)])


if __name__ == "__main__":
    sys.exit(run())
