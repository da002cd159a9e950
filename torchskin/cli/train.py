"""``torchskin train``: configuration-dependent rules boxes (or a classifier) learned from a generated dataset,
tuned to a false-alarm budget on the earthlib train spectra."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from ..errors import check_output_file
from .options import add_json, add_out_file, add_seed, check_number


def cmd_train(args: argparse.Namespace) -> int:
    from .. import boundaries as Bd

    check_output_file(args.out, "--out", (".pt",))
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1 (0 would write an untrained model), got {args.steps}")
    check_number("--pfa-budget", args.pfa_budget, 0, 0.999, "a false-alarm probability")
    check_number("--scene-budget", args.scene_budget, 0, 0.999, "a false-alarm probability")
    if args.method == "classifier":
        return _train_classifier(args)
    X, Y = Bd.load_skin_rows(args.data, sunlit_only=args.sunlit_only)
    scene = None if args.no_scene else Bd.load_scene_rows(args.data)
    opts = {"hidden": args.hidden, "steps": args.steps, "seed": args.seed}
    domain = Bd.domain_from_manifest(args.data)
    if args.method == "quantiles":
        opts["q"] = args.q
    else:
        opts.update(margin=args.margin, width_cost=args.width_cost, spread_cost=args.spread_cost)
    model, info = Bd.learn(X, Y, args.method, args.pfa_budget, domain=domain,
                           ndvn_quantile=None if args.no_ndvn_rule else Bd.NDVN_QUANTILE, scene=scene,
                           scene_budget=args.scene_budget, **opts)
    info["options"].pop("domain", None)
    info["light_classes"] = ["sunlit"] if args.sunlit_only else ["sunlit", "shadow"]
    scene_text = "" if scene is None else (f"; scene non-skin {info['pfa_scene_train']:.2e} <= {args.scene_budget:g} "
                                           f"of {info['scene_pixels']} training pixels")
    return _save_trained(args, Bd.save, model, info, (
        f"trained ({args.method}) on {info['rows']} {'sunlit ' if args.sunlit_only else ''}skin pixels, loss "
        f"{info['loss']:.5f}; NDVN rule d1 {info['ndvn_min']:.3f}; false-alarm scale {info['scale']:.3f}: worst Pfa "
        f"{info['pfa_train_worst']:.2e} <= {args.pfa_budget:g} on the earthlib train partition over "
        f"{info['calibration_configs']} configurations{scene_text}"))


def _save_trained(args: argparse.Namespace, save: Callable[..., None], model: Any, info: dict, text: str) -> int:
    """Record the training data in the summary, write the checkpoint, report."""
    from ..dataset.files import dataset_surface, manifest_sha256

    info.update(training_manifest_sha256=manifest_sha256(args.data), data=str(args.data),
                surface=dataset_surface(args.data))
    save(model, args.out, info)
    print(json.dumps({**info, "out": str(args.out)}) if args.json else f"{text}; wrote {args.out}")
    return 0


def _train_classifier(args: argparse.Namespace) -> int:
    from .. import boundaries as Bd
    from .. import classifier as Cl

    X, R, label, sunlit = Cl.load_rows(args.data)
    model, info = Cl.train_classifier(X, R, label, sunlit, hidden=max(args.hidden, 1), steps=args.steps,
                                      seed=args.seed, domain=Bd.domain_from_manifest(args.data),
                                      pfa_budget=args.pfa_budget,
                                      scene_budget=None if args.no_scene else args.scene_budget,
                                      sunlit_only=args.sunlit_only)
    return _save_trained(args, Cl.save, model, info, (
        f"trained (classifier) on {info['rows']} {'sunlit ' if args.sunlit_only else ''}skin pixels; threshold "
        f"{info['threshold']:.3f} (logit) for Pfa <= {args.pfa_budget:g} on the earthlib train partition over "
        f"{info['calibration_configs']} configurations; training skin kept {info['train_coverage']:.3f}, scene "
        f"non-skin {info['pfa_scene_train']:.2e}"))


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin train`` command."""
    tp = sub.add_parser("train", help="learn configuration-dependent boundaries from a generated dataset",
                        description="Learn configuration-dependent rules boxes (or a classifier) from a generated "
                                    "dataset, tuned to a false-alarm budget on the earthlib train spectra.")
    tp.add_argument("--data", required=True, help="dataset folder (torchskin generate)")
    add_out_file(tp, "the checkpoint (.pt)")
    tp.add_argument("--method", choices=("boxes", "quantiles", "classifier"), default="boxes",
                    help="boxes: most sunlit skin per configuration with the earthlib train spectra kept a margin "
                         "outside (default); quantiles: conditional quantiles of NDGRI and NDSI (pinball loss); "
                         "classifier: a configuration-conditioned MLP on scale-invariant band ratios "
                         "(torchskin.classifier), thresholded at the false-alarm budget")
    tp.add_argument("--margin", type=float, default=0.03,
                    help="boxes: distance (index units) kept from every earthlib train spectrum (default 0.03)")
    tp.add_argument("--width-cost", type=float, default=0.05,
                    help="boxes: cost per unit of box width, keeps the box tight (default 0.05)")
    tp.add_argument("--spread-cost", type=float, default=0.1,
                    help="boxes: cost of the boxes' spread over configurations (squared distance to their mean): "
                         "the box moves with the configuration only where the data pay for it (default 0.1)")
    tp.add_argument("--q", type=float, default=0.15, help="quantiles: quantile of the box edges (default 0.15)")
    tp.add_argument("--no-ndvn-rule", action="store_true",
                    help="boxes and quantiles: no visible/NIR rule (NDVN >= d1, d1 just below the training skin's "
                         "NDVN): the thesis's two indices alone")
    tp.add_argument("--steps", type=int, default=1500, help="optimisation steps (default 1500)")
    tp.add_argument("--hidden", type=int, default=32, help="MLP width (0: one constant box; default 32)")
    add_seed(tp, "the initial weights and batches")
    tp.add_argument("--pfa-budget", type=float, default=1e-3,
                    help="false-alarm budget on the earthlib train partition (default 1e-3)")
    tp.add_argument("--scene-budget", type=float, default=1e-4,
                    help="the largest share of the training dataset's own non-skin pixels "
                         "(clothing, ground and confusers, sunlit and shadowed) the boxes may call skin, held in "
                         "training and tuning (default 1e-4)")
    tp.add_argument("--no-scene", action="store_true",
                    help="hold only the earthlib spectra to a budget, not the dataset's non-skin pixels")
    tp.add_argument("--sunlit-only", action="store_true",
                    help="learn from sunlit skin only (default: sunlit and shadowed skin)")
    add_json(tp)
    tp.set_defaults(func=cmd_train)
    return tp
