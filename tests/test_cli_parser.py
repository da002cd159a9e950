"""The ``torchskin.cli`` package: every command registered in one parser, shared options defined once, and the
choices that come from a registry read from it."""

from __future__ import annotations

import argparse
import pkgutil
import subprocess
import sys

import pytest

import torchskin.cli
from torchskin.cli import build_parser, main, options
from torchskin.cli.parser import COMMANDS
from torchskin.render import light, materials, scene

EXPECTED = {"spectra", "render", "light", "experiment", "fit-skin", "fit-brdf", "generate", "dataset", "train",
            "export", "evaluate", "design-bands", "detect", "calibrate", "bench"}
#: modules of the package that are not commands
HELPERS = {"options", "parser", "cubes", "__main__"}


def _subparsers(ap: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    [action] = [a for a in ap._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings if s.startswith("--")}


@pytest.fixture(scope="module")
def commands() -> dict[str, argparse.ArgumentParser]:
    return _subparsers(build_parser())


def test_every_command_is_registered(commands):
    assert set(commands) == EXPECTED
    modules = {m.name for m in pkgutil.iter_modules(torchskin.cli.__path__)} - HELPERS
    assert modules == {module for _, module in COMMANDS}, "a command module of torchskin.cli is not in COMMANDS"
    for name, parser in commands.items():  # each has a handler, except the group of subcommands
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        handlers = [p.get_default("func") for p in (subs[0].choices.values() if subs else [parser])]
        assert all(callable(f) for f in handlers), name


def test_detect_and_calibrate_have_their_real_options(commands):
    """The full parser (the CLI reference's source) carries the torch-free commands' own options."""
    from torchskin.cli.calibrate import calibrate_parser
    from torchskin.cli.detect import detect_parser

    for name, standalone in (("detect", detect_parser()), ("calibrate", calibrate_parser())):
        assert set(_options(commands[name])) == set(_options(standalone)) >= {"--cube", "--out", "--json"}
        assert commands[name].format_help() == standalone.format_help()


def _shared(p: argparse.ArgumentParser) -> None:
    """Every shared builder on one parser: the reference for each option's definition."""
    for add in (options.add_json, options.add_device, options.add_sky, options.add_bands, options.add_atmosphere,
                options.add_illumination, options.add_frame, options.add_no_noise):
        add(p)


@pytest.mark.parametrize("flag", ["--json", "--device", "--sky", "--aerosol", "--water", "--ozone",
                                  "--pressure", "--day-of-year", "--illumination", "--width", "--height",
                                  "--max-megapixels", "--no-noise"])
def test_a_shared_option_reads_the_same_under_every_command(commands, flag):
    ref = argparse.ArgumentParser()
    _shared(ref)
    want = _options(ref)[flag]
    users = [name for name, p in commands.items() if flag in _options(p)]
    assert users, flag
    for name in users:
        got = _options(commands[name])[flag]
        assert (got.help, got.default, got.type, got.choices, got.metavar) == \
               (want.help, want.default, want.type, want.choices, want.metavar), f"{name} {flag}"


def test_json_and_device_are_shared_by_the_commands_that_take_them(commands):
    assert {n for n, p in commands.items() if "--json" in _options(p)} == EXPECTED - {"dataset"}
    assert {n for n, p in commands.items() if "--device" in _options(p)} == {"render", "experiment", "generate"}
    verify = _subparsers(commands["dataset"])["verify"]
    assert _options(verify)["--json"].help == options.JSON_HELP


def test_options_with_a_command_specific_part_read_alike(commands):
    """``--seed``, ``--out``, ``--bands`` and ``--panels`` differ in what they seed, hold, default to or add, not in how they are written."""
    for name, p in commands.items():
        opts = _options(p)
        if "--seed" in opts:
            assert opts["--seed"].help.startswith("seed of ") and opts["--seed"].help.endswith("(default 0)"), name
            assert opts["--seed"].default == 0 and opts["--seed"].type is int
        if "--panels" in opts:
            assert opts["--panels"].help.startswith("reference panels: lambertian (0.97 and 0.03), "), name
        if "--bands" in opts:
            assert opts["--bands"].help.startswith(options.BANDS_HELP + " (default: "), name
            assert opts["--bands"].metavar == options.BANDS_METAVAR
        if "--out" in opts:
            assert opts["--out"].help.startswith(("output folder: ", "output file: ")), name


def test_registry_choices(commands):
    """Panel kinds, skin BRDF kinds and light models come from their registries."""
    skin_brdfs = {k.removeprefix("skin-") for k, v in materials.KINDS.items() if k.startswith("skin-") and v.brdf}
    for name, p in commands.items():
        opts = _options(p)
        if "--panels" in opts:
            assert tuple(opts["--panels"].choices) == scene.PANEL_KINDS, name
        if "--surface" in opts:
            assert set(opts["--surface"].choices) == skin_brdfs == {"thesis", "conserving"}, name
        if "--illumination" in opts:
            assert tuple(opts["--illumination"].choices) == tuple(light.MODELS), name
    assert {n for n, p in commands.items() if "--panels" in _options(p)} == {"render", "experiment"}
    assert {n for n, p in commands.items() if "--illumination" in _options(p)} == {"render", "light"}
    assert all(k in materials.KINDS for k in scene.PANEL_KINDS)  # every panel kind renders


def test_a_newly_registered_kind_appears_without_an_edit():
    """Registering a light model or a skin BRDF kind puts it in the parsers' choices (and the help)."""
    light.register("toy-sky", light.MODELS["thesis"])
    materials.register("skin-toy", materials.KINDS["skin-thesis"])
    try:
        cmds = _subparsers(build_parser())
        for name in ("render", "light"):
            ill = _options(cmds[name])["--illumination"]
            assert "toy-sky" in ill.choices and "toy-sky" in ill.help
        for name in ("render", "experiment", "generate"):
            assert "toy" in _options(cmds[name])["--surface"].choices
    finally:
        light.unregister("toy-sky")
        materials.unregister("skin-toy")
    assert "toy-sky" not in _options(_subparsers(build_parser())["light"])["--illumination"].choices


def test_a_choice_outside_the_registry_is_one_line_exit_2(capsys):
    assert main(["light", "--illumination", "candle"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--illumination" in err and "spectrl2" in err


def test_build_parser_keeps_detect_and_calibrate_torch_free():
    """Building the detect and calibrate parts of the parser imports no torch (the rest may)."""
    script = ("import sys, argparse; from torchskin.cli import detect, calibrate; "
              "sub = argparse.ArgumentParser().add_subparsers(); detect.add_parser(sub); calibrate.add_parser(sub); "
              "assert 'torch' not in sys.modules")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_python_dash_m_runs_the_command_line():
    r = subprocess.run([sys.executable, "-m", "torchskin.cli", "calibrate", "--help"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("usage: torchskin calibrate"), r.stderr


def test_dataset_verify_imports_neither_torch_nor_the_renderer(tiny_dataset):
    """``torchskin dataset verify`` reads the folder's files only: its parser alone is built (``build_parser(only=)``),
    and a good dataset verifies (status 0) with no torch, open3d or ``torchskin.render`` in the process."""
    script = ("import sys; from torchskin.cli import main; rc = main(['dataset', 'verify', sys.argv[1]]); "
              "heavy = [m for m in ('torch', 'open3d', 'torchskin.render', 'torchskin.detectors') if m in sys.modules]; "
              "assert not heavy, heavy; sys.exit(rc)")
    r = subprocess.run([sys.executable, "-c", script, str(tiny_dataset)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout.lower()
