#!/usr/bin/env python
"""Pipeline step 1/5: generate the training and held-out datasets (embedded default configuration).

    python scripts/pipeline_generate.py [--work out/pipeline] [--train-configs 9600] [--heldout-configs 2400]

Writes WORK/train (seed 1) and WORK/heldout (seed 2); an existing complete dataset is kept (--resume)."""

import argparse
import sys

from torchskin.cli import main


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--train-configs", type=int, default=9600)
    ap.add_argument("--heldout-configs", type=int, default=2400)
    a = ap.parse_args(argv)
    for name, n, seed in (("train", a.train_configs, 1), ("heldout", a.heldout_configs, 2)):
        print(f"[generate] {name}: {n} configurations, seed {seed}", flush=True)
        rc = main(["generate", "--configs", str(n), "--seed", str(seed), "--out", f"{a.work}/{name}", "--resume"])
        if rc:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(run())
