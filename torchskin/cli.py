"""The ``torchskin`` command line. ``torchskin detect`` and ``torchskin calibrate`` run on numpy (and
onnxruntime) alone (the onboard path, ``torchskin.onboard_cli``: torch is not imported); every other command lives
in ``torchskin.commands``. Every command shares one error path (``torchskin.errors.run_command``): one line on
stderr, status 2 for bad input and 1 for a failure, a traceback only with ``--debug``."""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    """The whole command line as one parser: every command of ``torchskin.commands.build_parser`` with the
    onboard commands' own parsers (``torchskin.onboard_cli.detect_parser``, ``calibrate_parser``) in place of
    their entries there. ``main`` does not parse with it (``detect`` and ``calibrate`` must not import torch);
    it is what the documentation's CLI reference is generated from.

    >>> sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    >>> "--clip-negative" in sub.choices["detect"].format_help()
    True
    """
    from .commands import build_parser as commands_parser
    from .onboard_cli import calibrate_parser, detect_parser

    ap = commands_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    for name, make in (("detect", detect_parser), ("calibrate", calibrate_parser)):
        sub.choices[name] = make()
    return ap


def main(argv: list[str] | None = None) -> int:
    from .errors import run_command

    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    name = argv[0] if argv and not argv[0].startswith("-") else ""
    if name == "detect":
        from .onboard_cli import cli_detect

        return run_command("detect", lambda: cli_detect(argv[1:]), debug)
    if name == "calibrate":
        from .onboard_cli import cli_calibrate

        return run_command("calibrate", lambda: cli_calibrate(argv[1:]), debug)

    def full():
        from .commands import main as commands_main

        return commands_main(argv)

    return run_command(name or "", full, debug)


if __name__ == "__main__":
    sys.exit(main())
