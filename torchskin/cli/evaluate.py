"""``torchskin evaluate``: models (checkpoints or ONNX exports) against the static thesis box on a held-out
dataset: Pd by skin category, Pfa, decision-region areas."""

from __future__ import annotations

import argparse
import json
import sys

from ..errors import check_output_file, check_output_folder
from .options import add_json


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..evaluation import evaluate, table, write_figures
    from ..io import write_text

    if args.plots:
        check_output_folder(args.plots, "--plots")
    if args.save:
        check_output_file(args.save, "--save", (".json",))
    res = evaluate(args.data, args.model)  # complete: provenance and warnings included
    for w in res.get("warnings", ()):  # a model of another world: said, not refused
        print(f"torchskin evaluate: warning: {w}", file=sys.stderr)
    if args.plots:
        write_figures(res, args.plots)
    if args.save:
        write_text(args.save, json.dumps(res, indent=1))
    if args.json:
        print(json.dumps({k: res[k] for k in ("models", "learned", "static", "bins", "sun_zenith_ge_60", "warnings")
                          if k in res}))
    else:
        print(table(res))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin evaluate`` command."""
    ev = sub.add_parser("evaluate", help="Pd / Pfa of learned boundaries vs the static box on held-out data",
                        description="Compare models (checkpoints or ONNX exports) with the static thesis box on a "
                                    "held-out dataset: Pd by skin category, Pfa, decision-region areas; one table.")
    ev.add_argument("--data", required=True, help="held-out dataset folder")
    ev.add_argument("--model", required=True, action="append",
                    help="a model to evaluate (repeatable; one table row each, the static thesis box always last): "
                         "a checkpoint (.pt, of any detector kind), boundaries.onnx / baseline_box.onnx or "
                         "detector.onnx")
    ev.add_argument("--plots", metavar="DIR", help="write roc.png, pd_heatmap.png and boxes.png here")
    ev.add_argument("--save", metavar="FILE", help="write the full result (JSON, with ROC points) here")
    add_json(ev)
    ev.set_defaults(func=cmd_evaluate)
    return ev
