"""The whole ``torchskin`` argument parser: one subparser per command module of ``torchskin.cli``.

Each command module holds its handler and its parser (``add_parser(sub)``, which sets the handler as the
parsed namespace's ``func``); ``COMMANDS`` lists them in the order ``torchskin --help`` shows them.
"""

from __future__ import annotations

import argparse
import importlib

from .. import __version__
from ..errors import Parser

#: every command: (name on the command line, module of ``torchskin.cli``), in ``--help`` order
COMMANDS = (("spectra", "spectra"), ("render", "render"), ("light", "light"), ("experiment", "experiment"),
            ("fit-skin", "fit_skin"), ("fit-brdf", "fit_brdf"), ("generate", "generate"), ("dataset", "dataset"),
            ("train", "train"), ("export", "export"), ("evaluate", "evaluate"), ("detect", "detect"),
            ("calibrate", "calibrate"), ("bench", "bench"))
#: the commands ``torchskin.cli.main`` runs without importing torch (numpy and onnxruntime only)
TORCH_FREE = ("detect", "calibrate")

DESCRIPTION = ("Physics-based multispectral skin toolkit. Errors print one line (status 2: bad input; 1: a "
               "failure); --debug (anywhere on the command line) shows the traceback instead.")


def build_parser() -> argparse.ArgumentParser:
    """The complete parser, every command's options included (``detect`` and ``calibrate`` too, from their
    torch-free modules; the other commands' modules import torch)."""
    ap = Parser(prog="torchskin", description=DESCRIPTION)
    ap.add_argument("--version", action="version", version=f"torchskin {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=Parser)
    for _, module in COMMANDS:
        importlib.import_module(f"{__package__}.{module}").add_parser(sub)
    return ap


def run(argv: list[str]) -> int:
    """Parse ``argv`` with the whole parser and run the command's handler; errors propagate to
    ``torchskin.cli.main`` (``errors.run_command``)."""
    args = build_parser().parse_args(argv)
    return int(args.func(args))


__all__ = ["COMMANDS", "TORCH_FREE", "build_parser", "run"]
