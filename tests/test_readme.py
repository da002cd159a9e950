"""The command-line examples of the README and of the documentation pages (``docs/**/*.md``), run as written (in
a scratch folder, `exports/` linked in) and compared with the output the page prints: the same lines, word for
word, and every printed number equal to the real output within half a unit in the page's last shown digit
(values that change from run to run, wall-clock times, are named in ``VARIABLE``); JSON objects: the page's keys
and values. Examples that take minutes (the experiment at 512², the demo pipeline) are left to `make demo`; the
list below names the ones run here, and the demo pipeline's ``torchskin evaluate`` tables are compared with the
committed ``exports/evaluation*.json`` they were written from instead, as are the README's headline tables. The
``>>>`` examples of the pages run as doctests. No output block may show tqdm progress lines (they stand in for
the output they hide)."""

import doctest
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: every page whose examples are checked: the README, then the documentation's Markdown pages
PAGES = [README] + sorted(p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts and "api" not in p.parts)
#: command prefixes run here (every example starting with one of them, page by page, in page order)
RUN = ("torchskin spectra", "torchskin light", "torchskin render --out out/frame --json",
       "torchskin generate --configs 96 ", "torchskin dataset verify", "torchskin render --out frame --width 256", "torchskin render --out hs --width 256", "torchskin detect",
       "torchskin calibrate",
       # the detectors page's five-band camera, generate to detect
       "torchskin generate --bands rededge-mx", "torchskin train --data cam5", "torchskin export --model cam5.pt",
       "torchskin render --bands rededge-mx")
#: a printed number: not part of a word or file name (r544, shard-00001), with decimals and exponent as shown
NUMBER = r"(?<![\w.\-])[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?!\w)"
#: what legitimately differs from run to run, matched as any value: wall-clock durations in text ("2.41 s",
#: "in 3.60 s") and the JSON subtrees named here (``render --json``'s "timing_s": seconds per stage)
VARIABLE = re.compile(NUMBER + r" ?s\b")
VARIABLE_KEYS = {"timing_s"}
#: a tqdm progress line: "generate:  34%|███▍      | 3264/9600 [00:30<00:40, 157.55config/s]"
TQDM = re.compile(r"\d{1,3}%\||\[\d+:\d+(?::\d+)?<")


def readme_examples(page: Path = README) -> list[tuple[str, list[str]]]:
    """(command, printed lines) for every `$ torchskin ...` line of a page's code blocks (default the README)."""
    out, cmd, printed, in_block = [], None, [], False
    lines = page.read_text().splitlines()
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


def page_commands() -> list[tuple[Path, str, list[str], list[str]]]:
    """(page, command line, argv after ``torchskin``, printed lines) of every example run here, in page order;
    ``torchskin detect ... --flag`` is the page's last full example of that command, then these flags."""
    out = []
    for page in PAGES:
        last: dict[str, list[str]] = {}
        for cmd, printed in readme_examples(page):
            if not cmd.startswith(RUN):
                continue
            argv = shlex.split(cmd.split(" | ")[0])[1:]
            if "..." in argv:
                k = argv.index("...")
                argv = last[argv[0]] + argv[k + 1:]
            else:
                last[argv[0]] = argv
            out.append((page, cmd, argv, printed))
    return out


def command_chains(argvs: list[list[str]]) -> list[list[int]]:
    """The commands (indices into ``argvs``, in order) as chains that can run side by side: two commands are in
    one chain when one reads or writes what the other writes (an ``--out`` or ``--save-coefficients`` path, a
    file under it), or both are the same command without an ``--out`` (which may write its default file)."""
    parent = list(range(len(argvs)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    def writes(argv: list[str]) -> list[str]:
        return [argv[k + 1].rstrip("/") for k, a in enumerate(argv[:-1]) if a in ("--out", "--save-coefficients")]

    def touches(argv: list[str], written: list[str]) -> bool:  # an argument that is a written path or under one
        return any(x.rstrip("/") == w or x.startswith(w + "/") for w in written for x in argv)

    for j, b in enumerate(argvs):
        for i, a in enumerate(argvs[:j]):
            shared = touches(b, writes(a)) or touches(a, writes(b))
            if shared or (not writes(a) and not writes(b) and a[0] == b[0] and a[0] in ("spectra", "light")):
                parent[root(j)] = root(i)
    chains: dict[int, list[int]] = {}
    for i in range(len(argvs)):
        chains.setdefault(root(i), []).append(i)
    return list(chains.values())


def test_command_chains_keep_a_command_after_what_it_reads():
    argvs = [["render", "--out", "frame"], ["render", "--out", "hs"], ["detect", "--cube", "frame/r.npy"],
             ["calibrate", "--cube", "hs/s.hdr", "--out", "hs/refl.hdr"], ["generate", "--out", "data/"],
             ["dataset", "verify", "data/"], ["spectra"], ["spectra", "--all-presets"], ["light"]]
    assert sorted(command_chains(argvs)) == [[0, 2], [1, 3], [4, 5], [6, 7], [8]]


@pytest.mark.anny
@pytest.mark.slow
def test_page_examples_run_and_print_what_the_page_shows(tmp_path):
    """Each distinct command runs once; chains of commands that share no file run two at a time (the output is
    each command's own, so the comparison is the same as one after another)."""
    from concurrent.futures import ThreadPoolExecutor

    (tmp_path / "exports").symlink_to(ROOT / "exports")
    examples = page_commands()
    distinct = list(dict.fromkeys(tuple(argv) for _, _, argv, _ in examples))
    runs: dict[tuple[str, ...], subprocess.CompletedProcess] = {}  # one run per distinct command line

    def run_chain(chain: list[int]) -> None:
        for i in chain:
            runs[distinct[i]] = subprocess.run([sys.executable, "-m", "torchskin.cli", *distinct[i]], cwd=tmp_path,
                                               capture_output=True, text=True, timeout=600)

    with ThreadPoolExecutor(2) as pool:
        list(pool.map(run_chain, command_chains([list(a) for a in distinct])))
    ran, wrong = 0, []
    for page, cmd, argv, printed in examples:
        name = page.relative_to(ROOT)
        r = runs[tuple(argv)]
        got = (r.stdout if r.returncode == 0 else r.stderr).strip().splitlines()
        if " | tail -1" in cmd:
            got = got[-1:]
        want = [ln for ln in printed if ln.strip() and not ln.startswith("(")]
        assert "Traceback" not in r.stderr, (name, cmd, r.stderr)
        if want and want[0].lstrip().startswith("{"):  # JSON: the page's keys and values
            assert r.returncode == 0, (name, cmd, r.stderr)
            wrong += [f"{name}: {cmd}: {e}" for e in compare_json(readme_json(want), json.loads(r.stdout))]
        elif want:
            assert len(got) == len(want), (name, cmd, got, want)
            for g, w in zip(got, want):
                pattern, shown = line_pattern(w.strip())
                m = pattern.fullmatch(g.strip())
                if m is None:
                    wrong.append(f"{name}: {cmd}: page {w.strip()!r}, output {g.strip()!r}")
                    continue
                wrong += [f"{name}: {cmd}: page {s}, output {v} in {g.strip()!r}"
                          for s, v in zip(shown, m.groups()) if not agrees(float(v), s)]
            if any("error:" in w for w in want):
                assert r.returncode == 2 and not r.stdout, (name, cmd, r.returncode)  # an error: exit 2, stderr only
        else:
            assert r.returncode == 0, (name, cmd, r.stderr)
        ran += 1
    assert not wrong, "\n".join(wrong)
    assert ran >= 14  # every listed example was found and run (README and pages)


#: the demo pipeline's evaluate commands (docs/guide/detectors.md) and the committed results they printed
DEMO_EVALUATIONS = {"torchskin evaluate --data out/pipeline/heldout": "evaluation.json",
                    "torchskin evaluate --data out/pipeline/test": "evaluation_test.json"}


def test_demo_evaluate_tables_are_the_committed_exports():
    """The demo pipeline's printed ``torchskin evaluate`` tables are what ``evaluate.table`` prints for the
    committed ``exports/evaluation*.json``: every row, every digit (a progress line or a stale figure fails)."""
    from torchskin import evaluation

    found = 0
    for page in PAGES:
        for cmd, printed in readme_examples(page):
            prefix = next((p for p in DEMO_EVALUATIONS if cmd.startswith(p)), None)
            if prefix is None:
                continue
            table = [ln.rstrip() for ln in printed[:next(i for i, ln in enumerate(printed) if ln.startswith("("))]]
            result = json.loads((ROOT / "exports" / DEMO_EVALUATIONS[prefix]).read_text())
            assert table == [ln.rstrip() for ln in evaluation.table(result).splitlines()[:-1]], (page, cmd)
            found += 1
    assert found == len(DEMO_EVALUATIONS)


#: the README's headline tables: first header cell -> the export it reports; row label -> the figures (JSON paths)
HEADLINE_TABLES = {"fresh test set": "evaluation_test.json", "held-out set": "evaluation.json"}
HEADLINE_ROWS = {
    "Pd, sunlit skin": ["overall.pd_sunlit"],
    "Pd, sunlit skin without glint / glint-affected": ["overall.pd_sunlit_no_glint", "overall.pd_glint"],
    "Pd, sunlit skin, mean over configurations": ["overall.pd_sunlit_mean_over_configs"],
    "Pd, sunlit skin, sun zenith ≥ 60°, mean over configurations": ["sun_zenith_ge_60.pd_sunlit_mean_over_configs"],
    "Pd, shadowed skin": ["overall.pd_shadow"],
    "Pd, all skin of back-lit configurations": ["overall.pd_backlit"],
    "Pfa, earthlib test spectra (budget 1e-3)": ["overall.pfa"],
    "Pfa, scene non-skin pixels (budget 1e-4)": ["overall.pfa_scene"],
    "decision-region area, mean per configuration": ["area.mean"],
}


def markdown_tables(text: str) -> list[list[list[str]]]:
    """Every Markdown table of ``text`` as rows of cells (the header first, the rule row dropped)."""
    tables, rows = [], []
    for ln in text.splitlines() + [""]:
        if ln.startswith("|"):
            cells = [c.strip() for c in ln.strip().strip("|").split("|")]
            if not all(set(c) <= set("-: ") for c in cells):
                rows.append(cells)
        elif rows:
            tables.append(rows)
            rows = []
    return tables


def test_readme_headline_tables_are_the_committed_exports():
    checked = 0
    for table in markdown_tables(README.read_text()):
        export = HEADLINE_TABLES.get(table[0][0])
        if export is None:
            continue
        models = {m["name"]: m for m in json.loads((ROOT / "exports" / export).read_text())["models"]}
        names = [c.strip("`") for c in table[0][1:]]
        assert set(names) <= set(models), (export, names)
        assert [r[0] for r in table[1:]] == list(HEADLINE_ROWS), export  # every figure, in this order
        for label, *cells in table[1:]:
            for name, cell in zip(names, cells):
                shown = [v.strip().strip("*") for v in cell.split("/")]
                assert len(shown) == len(HEADLINE_ROWS[label]), (label, cell)
                for path, text in zip(HEADLINE_ROWS[label], shown):
                    value = models[name]
                    for key in path.split("."):
                        value = value[key]
                    assert agrees(value, text), f"{export} {name} {label}: README {text}, export {value}"
                    checked += 1
        assert len(names) >= 3
    assert checked >= 2 * 9 * 3  # both tables were found


@pytest.mark.slow
@pytest.mark.parametrize("page", [p for p in PAGES if ">>> " in p.read_text()], ids=lambda p: p.name)
def test_page_python_examples_run_as_doctests(page):
    failed, attempted = doctest.testfile(str(page), module_relative=False, verbose=False,
                                         optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert attempted > 0 and failed == 0, page


def test_output_blocks_hold_no_progress_bars():
    """A progress bar is not output: where a block of the README or of a documentation page shows one, it shows
    it instead of what the command prints (a table, a summary line)."""
    bars = []
    for page in PAGES:
        in_block = False
        for n, ln in enumerate(page.read_text().splitlines(), 1):
            if ln.startswith("```"):
                in_block = not in_block
            elif in_block and TQDM.search(ln):
                bars.append(f"{page.relative_to(ROOT)}:{n}: {ln}")
    assert not bars, "\n".join(bars)


def test_progress_bar_pattern_catches_a_tqdm_line():
    assert TQDM.search("generate:  34%|███▍      | 3264/9600 [00:30<00:40, 157.55config/s]")
    assert not TQDM.search("boundaries.pt                    0.722       0.733       0.645")


@pytest.mark.parametrize("prefix", RUN)
def test_every_listed_example_is_on_a_page(prefix):
    assert any(cmd.startswith(prefix) for page in PAGES for cmd, _ in readme_examples(page)), prefix


def test_readme_quickstart_shows_the_cli_from_spectra_to_the_onboard_detector():
    cmds = [cmd for cmd, _ in readme_examples()]
    for prefix in ("torchskin spectra", "torchskin render", "torchskin detect"):
        assert any(c.startswith(prefix) for c in cmds), prefix


def test_readme_links_render_on_a_package_index_and_exist_here():
    """The README is the package index page too (pyproject's readme): its images and page links are absolute links
    to this repository's files (relative ones break there), and every file they name exists in the checkout."""
    raw = "https://raw.githubusercontent.com/torchskin/torchskin/main/"
    blob = "https://github.com/torchskin/torchskin/blob/main/"
    text = README.read_text()
    images = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text)
    pages = re.findall(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)", text)
    assert images and pages
    for link in images:
        assert link.startswith(raw), f"README image {link!r} is not an absolute link into the repository"
        assert (ROOT / link[len(raw):]).is_file(), link
    for link in pages:
        if link.startswith("#"):
            continue
        assert link.startswith(("https://", "http://")), f"README link {link!r} is relative"
        if link.startswith(blob):
            assert (ROOT / link[len(blob):].partition("#")[0]).exists(), link
