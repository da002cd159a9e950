"""Deprecated: the commands moved to the ``torchskin.cli`` package, one module per command.

This module only re-exports them for code written against it (``torchskin.commands.main``,
``build_parser``, the ``cmd_*`` handlers); import from ``torchskin.cli`` and its command modules instead.
It will be removed in a later release.
"""

from __future__ import annotations

from .cli import build_parser
from .cli.bench import cmd_bench
from .cli.dataset import cmd_dataset_verify
from .cli.evaluate import cmd_evaluate
from .cli.experiment import cmd_experiment
from .cli.export import cmd_export
from .cli.fit_brdf import cmd_fit_brdf
from .cli.fit_skin import cmd_fit_skin
from .cli.generate import COMPILE_CHOICES, cmd_generate
from .cli.light import cmd_light
from .cli.options import ATMOSPHERE_OPTIONS, MAX_MEGAPIXELS, SURFACE_HELP
from .cli.parser import run as main
from .cli.render import cmd_render
from .cli.spectra import MAX_SAMPLE, cmd_spectra
from .cli.train import cmd_train

__all__ = ["ATMOSPHERE_OPTIONS", "COMPILE_CHOICES", "MAX_MEGAPIXELS", "MAX_SAMPLE", "SURFACE_HELP", "build_parser",
           "cmd_bench", "cmd_dataset_verify", "cmd_evaluate", "cmd_experiment", "cmd_export", "cmd_fit_brdf",
           "cmd_fit_skin", "cmd_generate", "cmd_light", "cmd_render", "cmd_spectra", "cmd_train", "main"]
