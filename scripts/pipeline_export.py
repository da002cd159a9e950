#!/usr/bin/env python
"""Pipeline step 4/5: export WORK/boundaries.pt to EXPORTS (boundaries.onnx, detector.onnx, model cards with
the evaluation), and keep the checkpoint, the evaluation and its plots beside them, with thesis_frame.png (the
exported detector on the thesis geometry, against the static box).

    python scripts/pipeline_export.py [--work out/pipeline] [--exports exports]"""

import argparse
import shutil
import sys
from pathlib import Path

from torchskin.cli import main
from torchskin.io import atomic_path


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--exports", default="exports")
    a = ap.parse_args(argv)
    work, out = Path(a.work), Path(a.exports)
    out.mkdir(parents=True, exist_ok=True)
    print(f"[export] to {out}", flush=True)
    rc = main(["export", "--model", str(work / "boundaries.pt"), "--out", str(out),
               "--metrics", str(work / "evaluation.json")])
    if rc:
        return rc
    for src, dst in ((work / "boundaries.pt", out / "boundaries.pt"), (work / "evaluation.json", out / "evaluation.json"),
                     (work / "plots" / "roc.png", out / "roc.png"), (work / "plots" / "pd_heatmap.png", out / "pd_heatmap.png"),
                     (work / "plots" / "boxes.png", out / "boxes.png")):
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
    from torchskin.evaluate import thesis_frame

    thesis_frame(out / "detector.onnx", plot=out / "thesis_frame.png")  # the shipped detector on the thesis geometry
    return 0


if __name__ == "__main__":
    sys.exit(run())
