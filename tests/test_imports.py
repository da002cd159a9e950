"""The package's import graph has no cycle: every ``import`` and ``from ... import`` in ``torchskin``, those inside
functions included (imports under ``if TYPE_CHECKING:`` only serve type checkers and do not count), read from the
source with ``ast``; a package's ``__init__`` counts as the package."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchskin"


def module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def imported(path: Path, modules: set[str], package_dir: Path = PACKAGE) -> set[str]:
    """The torchskin modules ``path`` imports (outside ``if TYPE_CHECKING:`` blocks)."""
    name = module_name(path, package_dir)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()

    def resolve(target: str) -> str | None:  # the deepest known module that ``target`` names
        while target and target not in modules:
            target = target.rpartition(".")[0]
        return target or None

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            out.update(m for a in node.names if (m := resolve(a.name)) and a.name.startswith("torchskin"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("torchskin"):
                for a in node.names:  # ``from . import tissue`` imports the module torchskin.tissue
                    m = resolve(f"{target}.{a.name}") if f"{target}.{a.name}" in modules else resolve(target)
                    if m:
                        out.add(m)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    out.discard(name)
    return out


def import_graph(package_dir: Path = PACKAGE) -> dict[str, set[str]]:
    files = sorted(package_dir.rglob("*.py"))
    modules = {module_name(p, package_dir) for p in files}
    return {module_name(p, package_dir): imported(p, modules, package_dir) for p in files}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


def test_the_cycle_finder_finds_a_lazy_import_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_walk_sees_imports_inside_functions_and_skips_type_checking(tmp_path):
    pkg = tmp_path / "torchskin"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .b import X\n"
                              "def f():\n    from . import c\n    import torchskin.b.inner\n")
    (pkg / "b").mkdir()
    (pkg / "b" / "__init__.py").write_text("from ..c import Y\n")
    (pkg / "c.py").write_text("")
    graph = import_graph(pkg)
    assert graph["torchskin.a"] == {"torchskin.c", "torchskin.b"} and graph["torchskin.b"] == {"torchskin.c"}
    (pkg / "c.py").write_text("def g():\n    from .a import f\n")  # a lazy import closes a cycle
    assert cycles(import_graph(pkg)) == [["torchskin.a", "torchskin.b", "torchskin.c"]]


def test_no_import_cycle_in_the_package():
    found = cycles(import_graph())
    assert not found, "import cycles (imports inside functions count): " + "; ".join(" <-> ".join(c) for c in found)


def with_packages(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """``graph`` with the packages Python runs on the way to a module: importing ``a.b.c`` runs ``a/__init__``
    and ``a/b/__init__`` first, so every importer of ``a.b.c`` reaches ``a`` and ``a.b`` too."""
    out = {m: set(deps) for m, deps in graph.items()}
    for m, deps in graph.items():
        for d in deps:
            parts = d.split(".")
            out[m].update(p for p in (".".join(parts[:i]) for i in range(1, len(parts))) if p in graph)
    return out


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module ``start`` loads, directly or through others (imports inside functions included)."""
    seen: set[str] = set()
    todo = [start]
    while todo:
        for d in graph.get(todo.pop(), ()):
            if d not in seen:
                seen.add(d)
                todo.append(d)
    return seen


def test_reachable_follows_the_packages_on_the_way():
    g = with_packages({"t": set(), "t.a": {"t.p.f"}, "t.p": {"t.p.learner"}, "t.p.f": set(), "t.p.learner": set()})
    assert reachable(g, "t.a") == {"t", "t.p", "t.p.f", "t.p.learner"}  # t.p's __init__ drags the learner in


#: the learners and what sits above them: the detector kinds that train, their registry, and the modules that judge
#: and export models
UPPER = {"torchskin.detectors.boxes", "torchskin.detectors.classifier", "torchskin.detectors.registry",
         "torchskin.evaluation", "torchskin.export", "torchskin.modelcard", "torchskin.cli"}
#: the layers below the learners: the index formulas, the datasets and the detectors' shared features
LOWER = ("torchskin.detect", "torchskin.bands", "torchskin.confusers", "torchskin.detectors",
         "torchskin.detectors.features", "torchskin.detectors.protocol", "torchskin.detectors.graphs")


def test_no_module_imports_upward():
    """Datasets, the index formulas and the detectors' shared modules never load a learner (nor what uses one),
    counting the package ``__init__`` files Python runs on the way (so ``torchskin.detectors``'s stays light)."""
    graph = with_packages(import_graph())
    lower = [m for m in graph if m in LOWER or m == "torchskin.dataset" or m.startswith("torchskin.dataset.")]
    assert "torchskin.dataset.generate" in lower and "torchskin.detectors.features" in lower
    bad = {m: sorted(reachable(graph, m) & UPPER) for m in lower}
    bad = {m: up for m, up in bad.items() if up}
    assert not bad, "modules that import upward: " + "; ".join(f"{m} -> {', '.join(up)}" for m, up in bad.items())
    # and the detectors' shared features do use the dataset's schema, as the generator does (not vacuous)
    assert "torchskin.dataset.schema" in reachable(graph, "torchskin.detectors.features")
    assert "torchskin.dataset.schema" in reachable(graph, "torchskin.dataset.generate")


def test_the_datasets_import_no_detector():
    """No module under ``torchskin/dataset`` loads ``torchskin.detectors`` (imports inside functions and the package
    ``__init__`` files on the way included): the dataset's schema (``dataset.schema``) sits below the detectors."""
    graph = with_packages(import_graph())
    datasets = [m for m in graph if m == "torchskin.dataset" or m.startswith("torchskin.dataset.")]
    assert {"torchskin.dataset.schema", "torchskin.dataset.generate", "torchskin.dataset.verify"} <= set(datasets)
    bad = {m: sorted(d for d in reachable(graph, m) if d.split(".")[:2] == ["torchskin", "detectors"])
           for m in datasets}
    bad = {m: d for m, d in bad.items() if d}
    assert not bad, "dataset modules that import the detectors: " + "; ".join(f"{m} -> {', '.join(d)}"
                                                                             for m, d in bad.items())


def test_dataset_verify_loads_no_renderer(tmp_path):
    """``torchskin dataset verify`` (its handler, ``cli.dataset``, and ``dataset.verify``) reads the folder's files
    alone: ``dataset.verify`` reaches no ``torchskin.render`` (statically), and the handler run in a fresh
    interpreter on a dataset leaves ``torchskin.render``, ``open3d`` and torch unloaded."""
    import hashlib
    import json
    import subprocess
    import sys

    graph = with_packages(import_graph())
    assert not {d for d in reachable(graph, "torchskin.dataset.verify") if d.startswith("torchskin.render")}
    # the handler imports the command line's package, whose parser (lazily) loads every command: checked running
    assert "torchskin.dataset.verify" in import_graph()["torchskin.cli.dataset"]
    shard = tmp_path / "shard-00000.parquet"
    shard.write_bytes(b"not parsed by verify")
    entry = {"name": shard.name, "rows": 3, "bytes": shard.stat().st_size,
             "sha256": hashlib.sha256(shard.read_bytes()).hexdigest()}
    (tmp_path / "_manifest.json").write_text(json.dumps({"schema_version": 6, "n_shards": 1, "shards": [entry]}))
    code = ("import argparse, sys\n"
            "from torchskin.cli.dataset import cmd_dataset_verify\n"
            f"status = cmd_dataset_verify(argparse.Namespace(dir={str(tmp_path)!r}, json=False))\n"
            "print('status', status)\n"
            "print('loaded', sorted(m for m in ('torchskin.render', 'open3d', 'torch', 'torchskin.dataset.generate')"
            " if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.startswith("ok: 1 shards, 3 rows") and "status 0" in out, out
    assert "loaded []" in out, out
