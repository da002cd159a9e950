#!/usr/bin/env python
"""Pipeline step 1/5: generate the training, held-out and fresh test datasets (embedded default configuration:
the thesis skin surface model, clothing drawn from each dataset's earthlib partition).

    python scripts/pipeline_generate.py [--work out/pipeline] [--train-configs 9600] [--heldout-configs 2400]
                                        [--test-configs 960] [--bands SPEC]

Writes WORK/train (seed 1, earthlib train partition), WORK/heldout (seed 2, test partition: used to compare
the models and choose the detector) and WORK/test (seed 3, test partition: never used for any choice, the
figures quoted for the exports); an existing complete dataset is kept (--resume), one rendered by another
renderer revision (``dataset.files.RENDER_REVISION``), another dataset schema (``SCHEMA_VERSION``) or from another
configuration (this torchskin's embedded defaults changed, or another seed or size) is regenerated (--overwrite)."""

import argparse
import sys
from pathlib import Path

from torchskin.cli import main
from torchskin.dataset.config import load_config
from torchskin.dataset.files import RENDER_REVISION, manifest
from torchskin.dataset.generate import SCHEMA_VERSION, same_draw
from torchskin.io import write_text


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--train-configs", type=int, default=9600)
    ap.add_argument("--heldout-configs", type=int, default=2400)
    ap.add_argument("--test-configs", type=int, default=960)
    ap.add_argument("--bands", default=None, help="the camera's bands (generate --bands; default the index bands)")
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    for name, n, seed, part in (("train", a.train_configs, 1, "train"), ("heldout", a.heldout_configs, 2, "test"),
                                ("test", a.test_configs, 3, "test")):
        print(f"[generate] {name}: {n} configurations, seed {seed}, earthlib {part} partition", flush=True)
        cfg = work / f"{name}.toml"
        write_text(cfg, f'[confusers]\npartition = "{part}"\n\n[clothing]\npartition = "{part}"\n')
        old = manifest(work / name)
        keep = "--resume"
        if old is not None and old.get("render_revision", 1) != RENDER_REVISION:
            print(f"[generate] {name}: rendered by renderer revision {old.get('render_revision', 1)}, regenerating "
                  f"with revision {RENDER_REVISION}", flush=True)
            keep = "--overwrite"
        elif old is not None and old.get("schema_version") != SCHEMA_VERSION:
            print(f"[generate] {name}: dataset schema {old.get('schema_version')}, regenerating with schema "
                  f"{SCHEMA_VERSION}", flush=True)
            keep = "--overwrite"
        elif old is not None and not same_draw(old, load_config(cfg, bands=a.bands), seed, n):
            print(f"[generate] {name}: drawn from another configuration, seed or size (this torchskin's defaults "
                  "changed?), regenerating", flush=True)
            keep = "--overwrite"
        bands = ["--bands", a.bands] if a.bands else []
        rc = main(["generate", "--config", str(cfg), "--configs", str(n), "--seed", str(seed), "--out",
                   f"{a.work}/{name}", keep, *bands])
        if rc:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(run())
