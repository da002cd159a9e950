"""``torchskin train``: a detector of any registered kind (``--method``) learned from a generated dataset, tuned
to a false-alarm budget on the earthlib train spectra."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from ..dataset.files import FRAME_SETS
from ..errors import check_output_file
from .options import add_json, add_out_file, add_seed, check_number

#: ``--scene-budget``'s default (the parser's default is None, so that an explicit budget with ``--no-scene`` is
#: refused rather than ignored)
SCENE_BUDGET = 1e-4


def cmd_train(args: argparse.Namespace) -> int:
    from ..detectors import registry
    from ..detectors.protocol import TrainRequest

    check_output_file(args.out, "--out", (".pt",))
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1 (0 would write an untrained model), got {args.steps}")
    check_number("--pfa-budget", args.pfa_budget, 0, 0.999, "a false-alarm probability")
    if args.scene_budget is not None and args.no_scene:  # None: not given (the parser's default)
        raise ValueError(f"--scene-budget {args.scene_budget:g} and --no-scene exclude each other: --no-scene holds no "
                         "budget on the dataset's non-skin pixels, so the budget would be ignored (drop one)")
    scene_budget = SCENE_BUDGET if args.scene_budget is None else args.scene_budget
    check_number("--scene-budget", scene_budget, 0, 0.999, "a false-alarm probability")
    model, info, text = registry.train(TrainRequest(
        args.data, args.method, pfa_budget=args.pfa_budget, scene_budget=scene_budget,
        use_scene=not args.no_scene, sunlit_only=args.sunlit_only, hidden=args.hidden, steps=args.steps,
        seed=args.seed, frames=args.frames, options=kind_options(args)))
    return _save_trained(args, registry.save, model, info, text)


def kind_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options of ``--method``'s kind given on the command line (``registry.train`` fills in the others'
    defaults); ``ValueError`` for a flag of another kind (it would be ignored)."""
    from ..detectors import registry

    kind = registry.kind_for_method(args.method, default=None)
    given = {}
    for k, cls in registry.kinds().items():
        for o in registry.options(cls):
            if not hasattr(args, o.name):  # not given (the parser's default is SUPPRESS)
                continue
            if k != kind.kind:
                raise ValueError(f"{o.cli_flag} is an option of --method {'|'.join(cls.methods)}, not of --method "
                                 f"{args.method} (it would be ignored)")
            given[o.name] = getattr(args, o.name)
    return given


def _add_kind_option(tp: argparse.ArgumentParser, o: Any) -> None:
    """A kind's option (``protocol.KindOption``) as a flag whose value, when given, lands on ``o.name``."""
    if o.value_type is bool:
        tp.add_argument(o.cli_flag, dest=o.name, action="store_false" if o.default else "store_true",
                        default=argparse.SUPPRESS, help=o.help)
    else:
        tp.add_argument(o.cli_flag, dest=o.name, type=o.value_type, default=argparse.SUPPRESS, help=o.help)


def _save_trained(args: argparse.Namespace, save: Callable[..., None], model: Any, info: dict, text: str) -> int:
    """Record the training data in the summary, write the checkpoint, report."""
    from ..dataset.files import dataset_surface, manifest, manifest_sha256

    info.update(training_manifest_sha256=manifest_sha256(args.data), data=str(args.data),
                surface=dataset_surface(args.data), light_model=str((manifest(args.data) or {}).get("light_model", "")))
    save(model, args.out, info)
    print(json.dumps({**info, "out": str(args.out)}) if args.json else f"{text}; wrote {args.out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin train`` command (``--method``: the registered kinds' methods)."""
    from ..detectors import registry  # imports torch: train is not one of the torch-free commands

    tp = sub.add_parser("train", help="learn configuration-dependent boundaries from a generated dataset",
                        description="Learn a configuration-dependent skin detector (--method: its kind) from a "
                                    "generated dataset, tuned to a false-alarm budget on the earthlib train spectra.")
    tp.add_argument("--data", required=True, help="dataset folder (torchskin generate)")
    add_out_file(tp, "the checkpoint (.pt)")
    tp.add_argument("--method", choices=registry.methods(), default=registry.methods()[0],
                    help="; ".join(registry.method_help(c) for c in registry.kinds().values()))
    for cls in registry.kinds().values():  # each kind's own options (refused with another kind's --method)
        for o in registry.options(cls):
            _add_kind_option(tp, o)
    tp.add_argument("--steps", type=int, default=1500, help="optimisation steps (default 1500)")
    tp.add_argument("--hidden", type=int, default=32, help="MLP width (0: one constant box; default 32)")
    add_seed(tp, "the initial weights and batches")
    tp.add_argument("--pfa-budget", type=float, default=1e-3,
                    help="false-alarm budget on the earthlib train partition (default 1e-3)")
    tp.add_argument("--scene-budget", type=float, default=None,
                    help="the largest share of the training dataset's own non-skin pixels "
                         "(clothing, ground and confusers, sunlit and shadowed) the boxes may call skin, held in "
                         f"training and tuning (default {SCENE_BUDGET:g}; refused with --no-scene)")
    tp.add_argument("--no-scene", action="store_true",
                    help="hold only the earthlib spectra to a budget, not the dataset's non-skin pixels (no "
                         "--scene-budget)")
    tp.add_argument("--sunlit-only", action="store_true",
                    help="learn from sunlit skin only (default: sunlit and shadowed skin)")
    tp.add_argument("--frames", choices=list(FRAME_SETS), default="line",
                    help="the frames to learn from: line (default), every frame whose reference panels are sunlit "
                         "and whose empirical line is a line (elm_line_valid), also where the panels receive less "
                         "light than sun-facing surfaces (a low sun grazing level panels: the detector meets such "
                         "frames in the field, and learning from them keeps more skin on physical frames); "
                         "physical: only the frames evaluation and calibration use (elm_valid)")
    add_json(tp)
    tp.set_defaults(func=cmd_train)
    return tp
