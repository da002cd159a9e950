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
            ("train", "train"), ("export", "export"), ("evaluate", "evaluate"), ("design-bands", "design_bands"),
            ("detect", "detect"),
            ("calibrate", "calibrate"), ("bench", "bench"))
#: the commands ``torchskin.cli.main`` runs without importing torch (numpy and onnxruntime only)
TORCH_FREE = ("detect", "calibrate")

DESCRIPTION = ("Physics-based multispectral skin toolkit. Errors print one line (status 2: bad input; 1: a "
               "failure); --debug (anywhere on the command line) shows the traceback instead.")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The complete parser, every command's options included (``detect`` and ``calibrate`` too, from their
    torch-free modules; most other commands' modules import torch), or, with ``only`` (a name of ``COMMANDS``),
    the parser of that one command: only its module is imported (``torchskin dataset verify`` imports neither
    torch nor the renderer)."""
    ap = Parser(prog="torchskin", description=DESCRIPTION)
    ap.add_argument("--version", action="version", version=f"torchskin {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=Parser)
    for name, module in COMMANDS:
        if only is None or name == only:
            importlib.import_module(f"{__package__}.{module}").add_parser(sub)
    return ap


def run(argv: list[str]) -> int:
    """Parse ``argv`` and run the command's handler; errors propagate to ``torchskin.cli.main``
    (``errors.run_command``). A line that starts with a command's name is parsed by that command's parser alone
    (``build_parser(only=...)``); anything else (``--help``, an unknown command) by the whole parser."""
    name = argv[0] if argv else ""
    args = build_parser(name if name in dict(COMMANDS) else None).parse_args(argv)
    return int(args.func(args))


__all__ = ["COMMANDS", "TORCH_FREE", "build_parser", "run"]
