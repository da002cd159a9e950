#!/usr/bin/env python
"""Pipeline step 4/5: export to EXPORTS and measure the exports on the fresh test set.

    python scripts/pipeline_export.py [--work out/pipeline] [--exports exports]

Writes detector.onnx (the checkpoint chosen in step 3, WORK/selection.json) and the pipeline models' exports
(``registry.pipeline_runs``' ``export_flag``: boundaries.onnx from WORK/boundaries.pt, baseline_box.onnx from
WORK/baseline_box.pt) with model cards quoting the held-out comparison; keeps the
checkpoints, the held-out evaluation and its plots beside them; evaluates the ONNX files on WORK/test (a
seed used for nothing else), with the pipeline's checkpoints that are not exported (the comparison kinds), into
evaluation_test.json and comparison_test.png; draws a kind's figure of its decision region where it has one
(<name>_region.png) and thesis_frame.png (the
exported detector on the thesis geometry, against the static box)."""

import argparse
import json
import shutil
import sys
from pathlib import Path

from torchskin.cli import main
from torchskin.detectors import registry
from torchskin.io import atomic_path

ROOT = Path(__file__).resolve().parents[1]
#: the graph `torchskin export` writes for each of its checkpoint flags (a pipeline run's ``export_flag``)
EXPORTED = {"--model": "boundaries.onnx", "--baseline": "baseline_box.onnx"}


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    ap.add_argument("--exports", default="exports")
    a = ap.parse_args(argv)
    work, out = Path(a.work), Path(a.exports)
    out.mkdir(parents=True, exist_ok=True)
    sel = json.loads((work / "selection.json").read_text())
    print(f"[export] to {out}; detector.onnx from {sel['detector']}", flush=True)
    runs = registry.pipeline_runs()
    flags = [x for r in runs if r.export_flag for x in (r.export_flag, str(work / r.checkpoint))]
    rc = main(["export", *flags, "--detector", str(work / sel["detector"]), "--detector-reason", sel["reason"], "--out", str(out),
               "--metrics", str(work / "evaluation.json")])
    if rc:
        return rc
    copies = [(work / f, out / f) for f in (*(r.checkpoint for r in runs), "evaluation.json", "selection.json")]
    copies += [(work / "plots" / f, out / f) for f in ("roc.png", "pd_heatmap.png", "boxes.png", "comparison.png")]
    for src, dst in copies:
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
    print("[export] the exports on the fresh test set (seed 3)", flush=True)
    exported = [EXPORTED[r.export_flag] for r in runs if r.export_flag in EXPORTED]
    others = [r.checkpoint for r in runs if r.export_flag not in EXPORTED and r.checkpoint != sel["detector"]]
    models = [x for m in (*exported, "detector.onnx", *others) for x in ("--model", str(out / m))]
    rc = main(["evaluate", "--data", str(work / "test"), *models, "--save", str(work / "evaluation_test.json"),
               "--plots", str(work / "plots_test")])
    if rc:
        return rc
    for src, dst in ((work / "evaluation_test.json", out / "evaluation_test.json"),
                     (work / "plots_test" / "comparison.png", out / "comparison_test.png")):
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
    for r in runs:  # a kind's own figure of its decision region, over the fresh test set
        kind = registry.get(registry.load_checkpoint(work / r.checkpoint).get("kind", registry.LEGACY_KIND))
        if hasattr(kind, "region_figure"):
            kind.region_figure(work / r.checkpoint, work / "test", out / f"{r.name}_region.png")
    from torchskin.evaluation import thesis_frame

    thesis_frame(out / "detector.onnx", plot=out / "thesis_frame.png")  # the shipped detector on the thesis geometry
    if out.resolve() == (ROOT / "exports").resolve():  # the shipped detector, packaged for pip users
        with atomic_path(ROOT / "torchskin" / "data" / "detector.onnx") as tmp:
            shutil.copyfile(out / "detector.onnx", tmp)
        print("[export] copied detector.onnx to torchskin/data/detector.onnx (the packaged default)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run())
