"""The ``torchskin`` command line. ``torchskin detect`` and ``torchskin calibrate`` run on numpy (and
onnxruntime) alone (the onboard path, ``torchskin.onboard_cli``: torch is not imported); every other command lives
in ``torchskin.commands``. Every command shares one error path (``torchskin.errors.run_command``): one line on
stderr, status 2 for bad input and 1 for a failure, a traceback only with ``--debug``."""

from __future__ import annotations

import sys


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
