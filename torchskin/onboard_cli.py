"""Deprecated: the onboard commands moved to ``torchskin.cli.detect`` and ``torchskin.cli.calibrate`` (their
file handling to ``torchskin.cli.cubes``), still numpy (and onnxruntime) only.

This module only re-exports them for code written against it; import from those modules instead. It will be
removed in a later release.
"""

from __future__ import annotations

from .cli.calibrate import calibrate_parser, cli_calibrate, parse_panel, parse_roi, read_coefficients
from .cli.cubes import load_cube, write_mask_png
from .cli.detect import FLAG_FOR_FEATURE, cli_detect, configuration_values, detect_parser

__all__ = ["FLAG_FOR_FEATURE", "calibrate_parser", "cli_calibrate", "cli_detect", "configuration_values",
           "detect_parser", "load_cube", "parse_panel", "parse_roi", "read_coefficients", "write_mask_png"]
