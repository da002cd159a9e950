"""``torchskin export``: checkpoints to ONNX (boundaries.onnx, baseline_box.onnx, detector.onnx) with metadata
and model cards."""

from __future__ import annotations

import argparse
import json
from typing import Any

from ..errors import check_input_file, check_output_folder
from .options import add_json, add_out_folder


def _checkpoint(path: str, what: str) -> tuple[Any, dict[str, Any]]:
    """(model, training summary) of a boundary or classifier checkpoint; one-line errors for bad files."""
    from pathlib import Path

    from ..detectors import registry

    check_input_file(path, what)  # missing, a folder or unreadable: says which
    model, ck = registry.load(path, what)
    return model, {**ck.get("meta", {}), "checkpoint": Path(path).name}


def cmd_export(args: argparse.Namespace) -> int:
    from ..detectors import registry
    from ..export import export, write_model_cards

    check_output_folder(args.out, "--out")
    if args.metrics:
        check_input_file(args.metrics, "--metrics", (".json",))
    model, train = _checkpoint(args.model, "--model")
    if registry.boxes_of(model) is None:
        raise ValueError(f"--model {args.model!r} is a {registry.kind_of(model)} model; boundaries.onnx needs a box "
                         "model (pass this one as --detector)")
    trains = {"boundaries": train}
    baseline = None
    if args.baseline:
        baseline, trains["baseline_box"] = _checkpoint(args.baseline, "--baseline")
        if registry.boxes_of(baseline) is None:
            raise ValueError(f"--baseline {args.baseline!r} is a {registry.kind_of(baseline)} model; it must be a box "
                             "model (torchskin train --hidden 0)")
    detector, trains["detector"] = (model, train) if not args.detector else _checkpoint(args.detector, "--detector")
    evaluation = None
    if args.metrics:
        try:
            with open(args.metrics) as fh:
                evaluation = json.load(fh)
        except (OSError, ValueError) as e:
            raise ValueError(f"cannot read --metrics {args.metrics!r}: {e}") from None
        if not isinstance(evaluation, dict) or not {"learned", "static"} <= set(evaluation):
            raise ValueError(f"--metrics {args.metrics!r} is not a torchskin evaluate --save result")
    reason = args.detector_reason or ("the configuration-dependent boxes of --model" if not args.detector else "")
    from ..evaluate import MIN_REFLECTANCE

    floor = (evaluation or {}).get("min_reflectance", MIN_REFLECTANCE)
    det_meta = {"detector_model": trains["detector"]["checkpoint"], "detector_reason": reason,
                "checkpoint": trains["detector"]["checkpoint"], "min_reflectance": f"{float(floor):g}"}
    paths = export(model, args.out, train.get("training_manifest_sha256", ""), surface=train.get("surface", ""),
                   baseline=baseline, detector=detector, detector_meta=det_meta, checkpoints={
                       k: v["checkpoint"] for k, v in trains.items()})
    paths.update(write_model_cards(args.out, train, evaluation, trains))
    print(json.dumps(paths) if args.json else "wrote " + ", ".join(paths.values()))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin export`` command."""
    xp = sub.add_parser("export", help="export a boundary checkpoint to boundaries.onnx and detector.onnx",
                        description="Export checkpoints to ONNX (boundaries.onnx, baseline_box.onnx, detector.onnx) with "
                                    "metadata and model cards.")
    xp.add_argument("--model", required=True, help="checkpoint (.pt) from torchskin train")
    add_out_folder(xp, "the ONNX graphs and model cards (e.g. exports/)")
    xp.add_argument("--baseline", metavar="PT", help="a single-box checkpoint (train --hidden 0) exported as "
                                                     "baseline_box.onnx, same inputs and outputs as boundaries.onnx")
    xp.add_argument("--detector", metavar="PT", help="the checkpoint detector.onnx is made from: a box model or a "
                                                     "classifier (default: --model)")
    xp.add_argument("--detector-reason", metavar="TEXT", help="why that model: recorded in detector.onnx's "
                                                              "metadata and model card")
    xp.add_argument("--metrics", metavar="EVAL.json", help="torchskin evaluate --save output for the model cards")
    add_json(xp)
    xp.set_defaults(func=cmd_export)
    return xp
