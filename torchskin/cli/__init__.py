"""The ``torchskin`` command line: one module per command, each with its handler and its parser.

``torchskin detect`` and ``torchskin calibrate`` run on numpy (and onnxruntime) alone: ``main`` dispatches them
to ``torchskin.cli.detect`` and ``torchskin.cli.calibrate`` without importing torch. Every other command is
parsed by the whole parser (``build_parser``, ``torchskin.cli.parser``), whose command modules import torch.
Options that several commands share are defined once, in ``torchskin.cli.options``. Every command shares one
error path (``torchskin.errors.run_command``): one line on stderr, status 2 for bad input and 1 for a failure,
a traceback only with ``--debug``.

Command modules: ``spectra``, ``render``, ``light``, ``experiment``, ``fit_skin``, ``fit_brdf``, ``generate``,
``dataset``, ``train``, ``export``, ``evaluate``, ``design_bands``, ``bench`` and the torch-free ``detect`` and ``calibrate``.
"""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    """The complete ``torchskin`` argument parser, every command and option included (imports torch for the
    commands other than ``detect`` and ``calibrate``); see ``torchskin.cli.parser``."""
    from .parser import build_parser as build

    return build()


def main(argv: list[str] | None = None) -> int:
    """Run one ``torchskin`` command line (``sys.argv[1:]`` by default) and return its exit status.

    ``--debug`` anywhere on the line re-raises errors instead of printing one line. ``detect`` and
    ``calibrate`` run without importing torch.
    """
    from ..errors import run_command

    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    name = argv[0] if argv and not argv[0].startswith("-") else ""
    if name == "detect":
        from .detect import cli_detect

        return run_command("detect", lambda: cli_detect(argv[1:]), debug)
    if name == "calibrate":
        from .calibrate import cli_calibrate

        return run_command("calibrate", lambda: cli_calibrate(argv[1:]), debug)

    def full() -> int:
        from .parser import run

        return run(argv)

    return run_command(name or "", full, debug)


__all__ = ["build_parser", "main"]
