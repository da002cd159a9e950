"""The README's command-line examples, run as written (in a scratch folder, `exports/` linked in) and compared
with the output the README prints: the same lines, word for word, and every printed number equal to the real
output within half a unit in the README's last shown digit (values that change from run to run, wall-clock
times, are named in ``VARIABLE``); JSON objects: the README's keys and values. Examples that take minutes (the
experiment at 512², the demo pipeline) are left to `make demo`; the list below names the ones run here. No
output block may show tqdm progress lines (they stand in for the output they hide)."""

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: command prefixes run here (every README example starting with one of them, in README order)
RUN = ("torchskin spectra", "torchskin light", "torchskin render --out out/frame --json",
       "torchskin generate --configs 96 ", "torchskin dataset verify", "torchskin render --out frame --width 256", "torchskin detect",
       "torchskin calibrate")
#: a printed number: not part of a word or file name (r544, shard-00001), with decimals and exponent as shown
NUMBER = r"(?<![\w.\-])[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?!\w)"
#: what legitimately differs from run to run, matched as any value: wall-clock durations in text ("2.41 s",
#: "in 3.60 s") and the JSON subtrees named here (``render --json``'s "timing_s": seconds per stage)
VARIABLE = re.compile(NUMBER + r" ?s\b")
VARIABLE_KEYS = {"timing_s"}
#: a tqdm progress line: "generate:  34%|███▍      | 3264/9600 [00:30<00:40, 157.55config/s]"
TQDM = re.compile(r"\d{1,3}%\||\[\d+:\d+(?::\d+)?<")


def readme_examples() -> list[tuple[str, list[str]]]:
    """(command, printed lines) for every `$ torchskin ...` line of the README's code blocks."""
    out, cmd, printed, in_block = [], None, [], False
    lines = README.read_text().splitlines()
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


def half_unit(shown: str) -> float:
    """Half a unit in the last digit of a number as written: "0.30294" 5e-6, "3.39e-04" 5e-7, "536" 0.5."""
    mant, _, exp = shown.lower().partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return 0.5 * 10.0 ** (int(exp or 0) - decimals)


def agrees(got: float, shown: str) -> bool:
    """``got`` rounds to the README's ``shown`` (1e-12 relative slack for the binary representation)."""
    return abs(got - float(shown)) <= half_unit(shown) + 1e-12 * abs(float(shown))


def line_pattern(want: str) -> tuple[re.Pattern, list[str]]:
    """A regex for the real output line matching README line ``want``: its words literal (runs of blanks as
    blanks), its numbers captured, its run-to-run values (``VARIABLE``) and "..." elisions as wildcards; and
    the numbers as written."""
    parts, shown, pos = [], [], 0
    token = re.compile(rf"(?P<var>{VARIABLE.pattern})|(?P<num>{NUMBER})|(?P<dots>\.\.\.)|(?P<blank>\s+)")
    for m in token.finditer(want):
        parts.append(re.escape(want[pos:m.start()]))
        if m.group("var"):
            parts.append(VARIABLE.pattern)
        elif m.group("num"):
            parts.append(f"({NUMBER})")
            shown.append(m.group())
        elif m.group("dots"):
            parts.append(".*?")
        else:
            parts.append(r"\s+")
        pos = m.end()
    parts.append(re.escape(want[pos:]))
    return re.compile("".join(parts)), shown


def compare_json(want, got, path: str = "") -> list[str]:
    """Where the README's JSON ``want`` (numbers as ``Shown``; None: elided) differs from the real ``got``."""
    if want is None or path.rsplit(".", 1)[-1] in VARIABLE_KEYS:
        return []
    if isinstance(want, dict):
        if not isinstance(got, dict):
            return [f"{path}: {got!r} is not an object"]
        return [e for k, v in want.items()
                for e in (compare_json(v, got[k], f"{path}.{k}") if k in got else [f"{path}.{k}: missing"])]
    if isinstance(want, list):
        if not isinstance(got, list) or (len(want) != len(got) and None not in want):
            return [f"{path}: {got!r} has not the README's {len(want)} items"]
        return [e for i, (w, g) in enumerate(zip(want, got)) for e in compare_json(w, g, f"{path}[{i}]")]
    if isinstance(want, Shown):
        ok = isinstance(got, (int, float)) and not isinstance(got, bool) and agrees(got, want.text)
        return [] if ok else [f"{path}: README {want.text}, output {got!r}"]
    return [] if want == got and type(want) is type(got) else [f"{path}: README {want!r}, output {got!r}"]


class Shown(float):
    """A README number with the text it was written as."""

    text: str

    def __new__(cls, text: str) -> "Shown":
        obj = super().__new__(cls, text)
        obj.text = text
        return obj


def readme_json(lines: list[str]):
    """The README's JSON block, its elisions ("{...}", "...") as None."""
    text = re.sub(r"\{\s*\.\.\.\s*\}|\[\s*\.\.\.\s*\]|\.\.\.", "null", " ".join(lines))
    return json.loads(text, parse_float=Shown, parse_int=Shown)


@pytest.mark.anny
@pytest.mark.slow
def test_readme_examples_run_and_print_what_the_readme_shows(tmp_path):
    (tmp_path / "exports").symlink_to(ROOT / "exports")
    last: dict[str, list[str]] = {}
    ran, wrong = 0, []
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
        if want and want[0].lstrip().startswith("{"):  # JSON: the README's keys and values
            assert r.returncode == 0, (cmd, r.stderr)
            wrong += [f"{cmd}: {e}" for e in compare_json(readme_json(want), json.loads(r.stdout))]
        elif want:
            assert len(got) == len(want), (cmd, got, want)
            for g, w in zip(got, want):
                pattern, shown = line_pattern(w.strip())
                m = pattern.fullmatch(g.strip())
                if m is None:
                    wrong.append(f"{cmd}: README {w.strip()!r}, output {g.strip()!r}")
                    continue
                wrong += [f"{cmd}: README {s}, output {v} in {g.strip()!r}"
                          for s, v in zip(shown, m.groups()) if not agrees(float(v), s)]
            if any("error:" in w for w in want):
                assert r.returncode == 2 and not r.stdout, (cmd, r.returncode)  # an error: exit 2, stderr only
        else:
            assert r.returncode == 0, (cmd, r.stderr)
        ran += 1
    assert not wrong, "\n".join(wrong)
    assert ran >= 10  # every listed example was found and run


def test_readme_output_blocks_hold_no_progress_bars():
    """A progress bar is not output: where a README block shows one, it shows it instead of what the command
    prints (a table, a summary line)."""
    bars, in_block = [], False
    for n, ln in enumerate(README.read_text().splitlines(), 1):
        if ln.startswith("```"):
            in_block = not in_block
        elif in_block and TQDM.search(ln):
            bars.append(f"README.md:{n}: {ln}")
    assert not bars, "\n".join(bars)


@pytest.mark.parametrize("prefix", RUN)
def test_every_listed_example_is_in_the_readme(prefix):
    assert any(cmd.startswith(prefix) for cmd, _ in readme_examples()), prefix
