"""The README's command-line examples, run as written (in a scratch folder, `exports/` linked in) and compared
with the output the README prints: the same shape (number of lines, their leading words, the keys of JSON
objects, the error line's prefix). Examples that take minutes (the experiment at 512², the demo pipeline) are
left to `make demo`; the list below names the ones run here."""

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: command prefixes run here (every README example starting with one of them, in README order)
RUN = ("torchskin spectra", "torchskin render --out out/frame --json", "torchskin generate --configs 96 ",
       "torchskin dataset verify", "torchskin render --out frame --width 256", "torchskin detect",
       "torchskin calibrate")


def readme_examples() -> list[tuple[str, list[str]]]:
    """(command, printed lines) for every `$ torchskin ...` line of the README's code blocks."""
    out, cmd, printed, in_block = [], None, [], False
    lines = (ROOT / "README.md").read_text().splitlines()
    i = 0
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("```"):
            if in_block and cmd:
                out.append((cmd, printed))
            cmd, printed, in_block = None, [], not in_block
        elif in_block and ln.startswith("$ torchskin"):
            if cmd:
                out.append((cmd, printed))
            text = ln[2:]
            while text.endswith("\\"):
                i += 1
                text = text[:-1] + " " + lines[i].strip()
            cmd, printed = text.split("  #")[0].strip(), []
        elif in_block and cmd:
            printed.append(ln)
        i += 1
    return out


def keys(obj) -> set[str]:
    if isinstance(obj, dict):
        return set(obj) | {k for v in obj.values() for k in keys(v)}
    if isinstance(obj, list):
        return {k for v in obj for k in keys(v)}
    return set()


@pytest.mark.anny
@pytest.mark.slow
def test_readme_examples_run_and_print_what_the_readme_shows(tmp_path):
    (tmp_path / "exports").symlink_to(ROOT / "exports")
    last: dict[str, list[str]] = {}
    ran = 0
    for cmd, printed in readme_examples():
        if not cmd.startswith(RUN):
            continue
        argv = shlex.split(cmd.split(" | ")[0])[1:]
        if "..." in argv:  # "torchskin detect ... --flag": the last full example of that command, then these flags
            k = argv.index("...")
            argv = last[argv[0]] + argv[k + 1:]
        else:
            last[argv[0]] = argv
        r = subprocess.run([sys.executable, "-m", "torchskin.cli", *argv], cwd=tmp_path, capture_output=True,
                           text=True, timeout=600)
        got = (r.stdout if r.returncode == 0 else r.stderr).strip().splitlines()
        if " | tail -1" in cmd:
            got = got[-1:]
        want = [ln for ln in printed if ln.strip() and not ln.startswith("(")]
        assert "Traceback" not in r.stderr, (cmd, r.stderr)
        if want and want[0].lstrip().startswith("{"):  # JSON: the README's keys are all there
            doc = json.loads(r.stdout)
            shown = set(re.findall(r'"(\w+)":', " ".join(want)))
            assert shown <= keys(doc), (cmd, shown - keys(doc))
            assert r.returncode == 0, (cmd, r.stderr)
        elif want:
            assert len(got) == len(want), (cmd, got, want)
            for g, w in zip(got, want):
                assert g.split()[:1] == w.split()[:1], (cmd, g, w)  # the same leading word
                if "error:" in w:
                    assert g.split("error:")[0] == w.split("error:")[0] and r.returncode != 0, (cmd, g)
        else:
            assert r.returncode == 0, (cmd, r.stderr)
        ran += 1
    assert ran >= 10  # every listed example was found and run


@pytest.mark.parametrize("prefix", RUN)
def test_every_listed_example_is_in_the_readme(prefix):
    assert any(cmd.startswith(prefix) for cmd, _ in readme_examples()), prefix
