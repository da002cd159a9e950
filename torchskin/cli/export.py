"""``torchskin export``: checkpoints to ONNX (boundaries.onnx, baseline_box.onnx, detector.onnx) with metadata
and model cards."""

from __future__ import annotations

import argparse
import json
from typing import Any

from ..errors import check_input_file, check_output_folder
from .options import add_json, add_out_folder


def _checkpoint(path: str, what: str) -> tuple[Any, dict[str, Any]]:
    """(model, training summary) of a checkpoint of any detector kind; one-line errors for bad files."""
    from pathlib import Path

    from ..detectors import registry

    check_input_file(path, what)  # missing, a folder or unreadable: says which
    model, ck = registry.load(path, what)
    return model, {**ck.get("meta", {}), "checkpoint": Path(path).name}


#: what makes a checkpoint's world: the training summary's keys (the skin surface model of the renders and, for
#: checkpoints that record it, the light model); a key a checkpoint does not record is not compared
WORLD_KEYS = ("surface", "light_model")
#: the export option names of the graphs
GRAPH_OPTIONS = {"boundaries": "--model", "baseline_box": "--baseline", "detector": "--detector"}


def check_worlds(trains: dict[str, dict[str, Any]], allow: bool = False) -> str:
    """``ValueError`` when the checkpoints of one export were trained in different worlds (``WORLD_KEYS``), unless
    ``allow`` (``--allow-mixed-worlds``); returns "" for one world, else the worlds as JSON (the ``mixed_worlds``
    metadata every graph then records)."""
    worlds = {}
    for key in WORLD_KEYS:
        seen = {name: str(t[key]) for name, t in trains.items() if t.get(key)}
        if len(set(seen.values())) > 1:
            worlds[key] = seen
    if not worlds:
        return ""
    if not allow:
        what = "; ".join(f"{key}: " + ", ".join(f"{GRAPH_OPTIONS[n]} {v}" for n, v in seen.items())
                         for key, seen in worlds.items())
        raise ValueError(f"the checkpoints were trained in different worlds ({what}): export each world on its "
                         "own, or pass --allow-mixed-worlds (recorded in every graph's metadata)")
    return json.dumps(worlds, sort_keys=True)


def cmd_export(args: argparse.Namespace) -> int:
    from ..detectors import registry
    from ..export import export, write_model_cards

    check_output_folder(args.out, "--out")
    if args.metrics:
        check_input_file(args.metrics, "--metrics", (".json",))
    model, train = _checkpoint(args.model, "--model")
    boxes = registry.boxes_of(model) is not None  # a model without boxes is exported as detector.onnx alone
    if not boxes and args.detector:
        raise ValueError(f"--model {args.model!r} is a {registry.kind_of(model)} model (no boxes for boundaries.onnx): "
                         "it is exported as detector.onnx, so --detector is refused with it (pass a box model as "
                         "--model, or drop --detector)")
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
    reason = args.detector_reason or ("" if args.detector else "the configuration-dependent boxes of --model" if boxes
                                      else f"the {registry.kind_of(model)} model of --model")
    from ..evaluation import MIN_REFLECTANCE

    floor = (evaluation or {}).get("min_reflectance", MIN_REFLECTANCE)
    det_meta = {"detector_model": trains["detector"]["checkpoint"], "detector_reason": reason,
                "checkpoint": trains["detector"]["checkpoint"], "min_reflectance": f"{float(floor):g}"}
    mixed = check_worlds(trains, args.allow_mixed_worlds)
    provenance = {name: {"training_manifest_sha256": t.get("training_manifest_sha256", ""),
                         "skin_surface_model": t.get("surface", ""),
                         **({"light_model": str(t["light_model"])} if t.get("light_model") else {}),
                         **({"mixed_worlds": mixed} if mixed else {})}
                  for name, t in trains.items()}
    paths = export(model, args.out, train.get("training_manifest_sha256", ""), surface=train.get("surface", ""),
                   baseline=baseline, detector=detector, detector_meta=det_meta, checkpoints={
                       k: v["checkpoint"] for k, v in trains.items()}, provenance=provenance)
    paths.update(write_model_cards(args.out, train, evaluation, trains))
    print(json.dumps(paths) if args.json else "wrote " + ", ".join(paths.values()))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin export`` command."""
    xp = sub.add_parser("export", help="export a boundary checkpoint to boundaries.onnx and detector.onnx",
                        description="Export checkpoints to ONNX (boundaries.onnx, baseline_box.onnx, detector.onnx) with "
                                    "metadata and model cards.")
    xp.add_argument("--model", required=True, help="checkpoint (.pt) from torchskin train (a model without boxes: "
                                                    "detector.onnx alone)")
    add_out_folder(xp, "the ONNX graphs and model cards (e.g. exports/)")
    xp.add_argument("--baseline", metavar="PT", help="a single-box checkpoint (train --hidden 0) exported as "
                                                     "baseline_box.onnx, same inputs and outputs as boundaries.onnx")
    xp.add_argument("--detector", metavar="PT", help="the checkpoint detector.onnx is made from: a model of any "
                                                     "detector kind (default: --model)")
    xp.add_argument("--detector-reason", metavar="TEXT", help="why that model: recorded in detector.onnx's "
                                                              "metadata and model card")
    xp.add_argument("--metrics", metavar="EVAL.json", help="torchskin evaluate --save output for the model cards")
    xp.add_argument("--allow-mixed-worlds", action="store_true",
                    help="combine checkpoints trained under different skin surface or light models (refused "
                         "otherwise; recorded as mixed_worlds in every graph's metadata)")
    add_json(xp)
    xp.set_defaults(func=cmd_export)
    return xp
