"""The documentation site builds with warnings as errors (what ``make docs`` runs), and what it must hold is in
it: a page for every module of the package (autosummary, recursive), and a command-line reference that lists
every command and option of the parsers."""

import argparse
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import torchskin
from torchskin.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def _walk(parser: argparse.ArgumentParser, name: str = "torchskin"):
    """(command name, its parser) for the parser and every subcommand below it."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child, sub in action.choices.items():
                yield from _walk(sub, f"{name} {child}")


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("html")
    r = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(ROOT / "docs"),
                        str(out), "-d", str(out / ".doctrees")], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-6000:]
    return out


@pytest.mark.slow
def test_docs_build_without_warnings_and_document_every_module(site):
    modules = ["torchskin"] + [m.name for m in pkgutil.walk_packages(torchskin.__path__, "torchskin.")
                               if not any(part.startswith("_") for part in m.name.split("."))]
    missing = [m for m in modules if not (site / "api" / f"{m}.html").exists()]
    assert not missing, missing
    for page in ("index", "physics", "benchmarks", "validation", "reproducibility", "data", "cli", "api",
                 "guide/rendering", "guide/detectors", "guide/datasets", "guide/onboard"):
        assert (site / f"{page}.html").exists(), page
    # the figures are in the pages, not only in the folder
    physics, detectors = (site / "physics.html").read_text(), (site / "guide" / "detectors.html").read_text()
    assert "_images/surface_energy.png" in physics and "_images/issa_fit.png" in physics
    assert "_images/comparison.png" in detectors and "_images/thesis_frame.png" in detectors
    assert "_images/frame_costs.png" in (site / "benchmarks.html").read_text()
    pages = "".join(p.read_text() for p in site.rglob("*.html"))
    figures = sorted(p.name for p in [*(ROOT / "docs").glob("*.png"), *(ROOT / "exports").glob("*.png")])
    assert [f for f in figures if f"_images/{f}" not in pages] == []  # every committed figure is shown on a page


@pytest.mark.slow
def test_cli_reference_lists_every_command_and_option(site):
    html = (site / "cli.html").read_text()
    missing = []
    for name, parser in _walk(build_parser()):
        if f">{name}<" not in html:
            missing.append(name)
        for action in parser._actions:
            for opt in action.option_strings:
                if opt not in html:
                    missing.append(f"{name} {opt}")
    assert not missing, missing
    assert html.count("--clip-negative") >= 1 and "torchskin detect" in html  # the torch-free parsers are in


def test_the_dataset_column_table_is_the_schema():
    """docs/guide/datasets.md lists every Parquet column with the type, meaning and unit the generator writes
    (``dataset.schema.COLUMNS``), in order: a column added or reworded in the code shows up here."""
    from pathlib import Path

    from torchskin.dataset.schema import COLUMNS

    text = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "datasets.md").read_text()
    rows = [ln for ln in text.splitlines() if ln.startswith("| `")]
    table = {}
    for ln in rows:
        cells = [c.strip() for c in ln.strip("|").split(" | ")]
        if len(cells) == 4 and cells[0].strip("`") in COLUMNS:
            table[cells[0].strip("`")] = (cells[1], cells[2].replace("&#124;", "|"), cells[3])
    assert list(table) == list(COLUMNS)
    for k, (t, d, u) in COLUMNS.items():
        assert table[k] == (t, d, u), k
