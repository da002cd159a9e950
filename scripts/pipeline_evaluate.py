#!/usr/bin/env python
"""Pipeline step 3/5: calibrate the trained models to the false-alarm budgets on WORK/heldout, compare them there
(with the static thesis box) and choose the detector to ship.

    python scripts/pipeline_evaluate.py [--work out/pipeline]

Each model of the pipeline (``registry.pipeline_runs``), WORK/<model>.pt, is first calibrated on the held-out set (evaluation.calibrate_to_budget: one scalar per model,
the box scale or the classifier's threshold, so that held-out scene non-skin Pfa <= 1e-4 and earthlib test Pfa
<= 1e-3) from the trained WORK/<model>.trained.pt; the calibration is recorded in the checkpoint's metadata. Writes WORK/evaluation.json (every model: Pd sunlit / glint-affected / shadowed, Pfa earthlib test and scene
non-skin by family, decision-region areas, per-bin figures), WORK/plots/{roc,pd_heatmap,boxes,comparison}.png
and WORK/selection.json (the checkpoint detector.onnx is made from, and why: evaluation.select_detector)."""

import argparse
import json
import sys
from pathlib import Path

from torchskin.cli import main
from torchskin.detectors import registry
from torchskin.evaluation import calibrate_to_budget, select_detector
from torchskin.io import write_text


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="out/pipeline")
    a = ap.parse_args(argv)
    MODELS = [r.checkpoint for r in registry.pipeline_runs()]
    for m in MODELS:
        trained = Path(a.work) / m.replace(".pt", ".trained.pt")  # pipeline_train's output
        rec = calibrate_to_budget(trained, f"{a.work}/heldout", Path(a.work) / m)
        print(f"[evaluate] {m}: {rec['knob']} {rec['before']:.4g} -> {rec['after']:.4g} for held-out scene Pfa "
              f"{rec['pfa_scene']:.2e} <= {rec['scene_budget']:g}", flush=True)
    print("[evaluate] held-out configurations and earthlib test spectra", flush=True)
    models = [x for m in MODELS for x in ("--model", f"{a.work}/{m}")]
    rc = main(["evaluate", "--data", f"{a.work}/heldout", *models, "--plots", f"{a.work}/plots", "--save",
               f"{a.work}/evaluation.json"])
    if rc:
        return rc
    with open(f"{a.work}/evaluation.json") as fh:
        name, reason = select_detector(json.load(fh))
    print(f"[evaluate] detector.onnx from {name}: {reason}", flush=True)
    write_text(f"{a.work}/selection.json", json.dumps({"detector": name, "reason": reason}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run())
