"""``torchskin bench``: throughput benchmarks (km, render, fit, dataset, detector_onnx, materials)."""

from __future__ import annotations

import argparse
import json

from .options import add_json


def cmd_bench(args: argparse.Namespace) -> int:
    """Run ``torchskin bench`` (``torchskin.bench.run``): each benchmark's figures, or everything with ``--json``."""
    from .. import bench

    if args.only is not None and not [x for x in args.only.split(",") if x.strip()]:
        raise ValueError("--only needs benchmark names, e.g. --only render,materials")
    only = [x.strip() for x in args.only.split(",") if x.strip()] if args.only else None
    res = bench.run(only, compile=args.compile)
    if args.json:
        print(json.dumps(res))
    else:  # each benchmark's figures, numbers only (--json has everything)
        for name, r in res.items():
            figures = [f"{k} {v:.4g}" for k, v in r.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
            print(f"{name:<14}" + ", ".join(figures))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin bench`` command."""
    bp = sub.add_parser("bench", help="benchmarks (JSON with --json)",
                        description="Throughput benchmarks: km, render, fit, dataset, detector_onnx, materials.")
    add_json(bp)
    bp.add_argument("--only", metavar="NAMES", help="comma-separated benchmark names (default: all)")
    bp.add_argument("--compile", action="store_true",
                    help="km: also measure the compiled skin model (slow start); render and dataset always time "
                         "the eager and the compiled kernels side by side")
    bp.set_defaults(func=cmd_bench)
    return bp
