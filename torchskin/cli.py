"""The ``torchskin`` command line. ``torchskin detect`` and ``torchskin calibrate`` run on numpy (and
onnxruntime) alone (the onboard path: torch is not imported); every other command lives in
``torchskin.commands``."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "detect":
        from .onboard import cli_detect

        return cli_detect(argv[1:])
    if argv and argv[0] == "calibrate":
        from .onboard import cli_calibrate

        return cli_calibrate(argv[1:])
    from .commands import main as full

    return full(argv)


if __name__ == "__main__":
    sys.exit(main())
