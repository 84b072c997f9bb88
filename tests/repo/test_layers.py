"""The shape of the code: no import circle, no import that points up the layers, no module over 700 lines.

The layer order is the one docs/development.md draws ("Layers"): a module may import its own layer
and the layers below it, never one above.  Imports inside functions count too (they are for
start-up time only and point down like the others).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("testbed", "plants", "attackers")
MAX_LINES = 700
GENERATED = {"testbed/loop/_dop853.py"}  # tools/gen_dop853.py writes it


def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for pk in PACKAGES:
        for p in sorted((ROOT / pk).rglob("*.py")):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            ispkg = parts[-1] == "__init__"
            out[".".join(parts[:-1] if ispkg else parts)] = (p, ispkg)
    return out


MODULES = _modules()


def _targets(mod: str, ispkg: bool, node: ast.Import | ast.ImportFrom) -> list[str]:
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:
            base = mod.split(".") if ispkg else mod.split(".")[:-1]
            base = base[:len(base) - (node.level - 1)]
            pkg = ".".join(base + ([node.module] if node.module else []))
        else:
            pkg = node.module or ""
        names = [f"{pkg}.{a.name}" if f"{pkg}.{a.name}" in MODULES else pkg for a in node.names]
    out = []
    for n in names:
        while n and n not in MODULES:
            n = n.rpartition(".")[0]
        if n:
            out.append(n)
    return out


def _edges() -> dict[str, dict[str, int]]:
    """module -> {imported module: line}, every import of the module (top level and inside functions)."""
    edges: dict[str, dict[str, int]] = {}
    for mod, (path, ispkg) in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for t in _targets(mod, ispkg, node):
                    if t != mod:
                        edges.setdefault(mod, {}).setdefault(t, node.lineno)
    return edges


EDGES = _edges()


def _cycles(edges: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out = []
    for root in sorted(set(edges) | {b for t in edges.values() for b in t}):
        if root in index:
            continue
        work = [(root, iter(edges.get(root, ())))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(edges.get(w, ()))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def _layers() -> list[list[str]]:
    """The layer order of docs/development.md, top first: each layer a list of module prefixes."""
    text = (ROOT / "docs" / "development.md").read_text()
    block = text.split("## Layers", 1)[1].split("```", 2)[1]
    layers = []
    for line in block.strip("\n").splitlines():
        names = line.split("  ")[0].split()
        if names:
            layers.append([n.rstrip("/").removesuffix(".py").removesuffix("/__init__").replace("/", ".")
                           for n in names])
    return layers


def _layer_of(mod: str, layers: list[list[str]]) -> int | None:
    best, found = -1, None
    for i, prefixes in enumerate(layers):
        for p in prefixes:
            if (mod == p or mod.startswith(p + ".")) and len(p) > best:
                best, found = len(p), i
    return found


def test_the_layer_order_is_read():
    layers = _layers()
    assert len(layers) >= 8
    assert _layer_of("testbed.cli", layers) < _layer_of("testbed.live.launcher", layers)
    assert _layer_of("testbed.nodes.plant", layers) < _layer_of("testbed.wire.messages", layers)
    assert _layer_of("testbed.loop.flow", layers) < _layer_of("plants.base", layers)


def test_every_module_has_a_layer():
    layers = _layers()
    missing = [m for m in MODULES if _layer_of(m, layers) is None]
    assert not missing, f"modules in no layer of docs/development.md: {missing}"


def test_no_import_circle():
    cycles = _cycles(EDGES)
    detail = [[f"{a} -> {b} (line {EDGES[a][b]})" for a in c for b in EDGES.get(a, {}) if b in c] for c in cycles]
    assert not cycles, f"import circles: {detail}"


def test_the_cycle_finder_finds_one():
    assert _cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b": 1}, "b": {"c": 1}}) == []


def test_no_import_points_up():
    layers = _layers()
    up = []
    for a, targets in EDGES.items():
        la = _layer_of(a, layers)
        for b, line in targets.items():
            lb = _layer_of(b, layers)
            if la is not None and lb is not None and lb < la:
                up.append(f"{a} (line {line}) imports {b}, a higher layer")
    assert not up, "\n".join(up)


def test_plants_and_attackers_never_import_testbed():
    bad = [f"{a} -> {b}" for a, t in EDGES.items() if a.split(".")[0] in ("plants", "attackers")
           for b in t if b.split(".")[0] == "testbed"]
    assert not bad, bad


def test_no_module_over_700_lines():
    long = []
    for path, _ in MODULES.values():
        rel = path.relative_to(ROOT).as_posix()
        n = len(path.read_text().splitlines())
        if n > MAX_LINES and rel not in GENERATED:
            long.append(f"{rel}: {n} lines")
    assert not long, f"modules over {MAX_LINES} lines (split them by responsibility): {long}"


# ---------------------------------------------------------------------------------------------- the tests' own shape
TESTS = ROOT / "tests"


def imports_of_test_modules(source: str) -> list[tuple[int, str]]:
    """(line, module) of every import of a test module (``test_*``) in ``source``: ``import test_x``, ``from
    test_x import ...``, inside functions too, and ``importlib.import_module("test_x")``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0].startswith("test_")]
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0].startswith("test_"):
            found.append((node.lineno, node.module))
        elif (isinstance(node, ast.Call) and ast.unparse(node.func) in ("importlib.import_module", "import_module",
                                                                         "__import__")
              and node.args and isinstance(node.args[0], ast.Constant) and str(node.args[0].value).startswith("test_")):
            found.append((node.lineno, node.args[0].value))
    return found


@pytest.mark.slow  # half a second or more on a warm cache
def test_no_test_module_imports_another():
    """What tests share lives in tests/helpers/, tests/conftest.py (fixtures) or tests/failclosed.py (the
    rerun policy, capabilities): a test module never imports another (that would run its tests' set-up,
    tie the two together, and hide the shared part)."""
    bad = [f"{p.relative_to(ROOT)}:{line} imports {mod}" for p in sorted(TESTS.rglob("*.py"))
           for line, mod in imports_of_test_modules(p.read_text())]
    assert not bad, "\n".join(bad)


def test_the_test_import_finder_finds_one():
    src = ("import json\nimport test_a\nfrom test_b import x\nfrom helpers import tb\n"
           "def f():\n    import test_c as c\n    from . import test_d\n"
           "    importlib.import_module('test_e')\n    import_module('helpers')\n")
    assert imports_of_test_modules(src) == [(2, "test_a"), (3, "test_b"), (6, "test_c"), (8, "test_e")]


def _test_layout() -> list[str]:
    """The folders of tests/ that docs/development.md names ("Where a test goes"), in its order."""
    text = (ROOT / "docs" / "development.md").read_text()
    block = text.split("### Where a test goes", 1)[1].split("```", 2)[1]
    return [line.split()[0] for line in block.splitlines() if line.startswith("tests/")]


def test_every_test_module_is_in_a_folder_the_docs_name():
    """A newcomer finds a test by the layer it is about: every ``test_*.py`` is in a folder that
    docs/development.md names and says what it holds, every folder named there exists, and no two test
    modules share a file name (pytest imports them by it: the one ``__init__.py`` of tests/ is the helpers package's)."""
    layout = _test_layout()
    folders = {e.rstrip("/") for e in layout if e.endswith("/")}
    assert {"tests/core", "tests/sim", "tests/live", "tests/helpers", "tests/repo"} <= folders, layout
    missing = [e for e in layout if not (ROOT / e).exists()]
    assert not missing, f"named in docs/development.md but not there: {missing}"
    mods = sorted(TESTS.rglob("test_*.py"))
    assert len(mods) > 50
    astray = [str(p.relative_to(ROOT)) for p in mods if p.parent.relative_to(ROOT).as_posix() not in folders]
    assert not astray, f"test modules outside the folders of docs/development.md (## Tests): {astray}"
    names: dict[str, list[str]] = {}
    for p in mods:
        names.setdefault(p.name, []).append(str(p.relative_to(ROOT)))
    twice = {n: ps for n, ps in names.items() if len(ps) > 1}
    assert not twice, f"test modules of one name: {twice}"
    assert sorted(TESTS.rglob("__init__.py")) == [TESTS / "helpers" / "__init__.py"]  # one package: tests/helpers
