"""Type hints on every public function: each parameter (but ``self``/``cls``) and the return annotated.

A public function is a module-level function or a method of a public class whose name does not start with
``_``, in a module of ``testbed/``, ``plants/`` or ``attackers/`` that is not private (no part of its path
starts with ``_`` but ``__init__.py``).  mypy checks the bodies of annotated functions only
(tests/repo/test_types.py), so an unannotated one is unchecked: this test lists them.

``python tests/repo/test_annotations.py`` prints the coverage and the functions still unannotated.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("testbed", "plants", "attackers")

# Functions still to annotate ("path:Class.name"). This list must only shrink: annotate a function and take it
# off; never add one (a new public function comes annotated).
NOT_YET_ANNOTATED: set[str] = set()


def _private_module(rel: Path) -> bool:
    return any(part.startswith("_") and part != "__init__.py" for part in rel.parts)


def unannotated(source: str, where: str) -> tuple[int, list[str]]:
    """(public functions in ``source``, those of them lacking an annotation) as ``where:Class.name``."""
    found: list[str] = []
    total = 0

    def visit(body: list[ast.stmt], cls: str | None) -> None:
        nonlocal total
        for node in body:
            if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                visit(node.body, node.name if cls is None else f"{cls}.{node.name}")
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
                total += 1
                a = node.args
                params = [*a.posonlyargs, *a.args, *a.kwonlyargs, *filter(None, (a.vararg, a.kwarg))]
                static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in node.decorator_list)
                if cls is not None and not static and params and params[0].arg in ("self", "cls"):
                    params = params[1:]
                if node.returns is None or any(p.annotation is None for p in params):
                    found.append(f"{where}:{'' if cls is None else cls + '.'}{node.name}")

    visit(ast.parse(source, where).body, None)
    return total, found


def survey() -> tuple[int, list[str]]:
    """(public functions of the three packages, those lacking an annotation)."""
    total, missing = 0, []
    for pk in PACKAGES:
        for p in sorted((ROOT / pk).rglob("*.py")):
            rel = p.relative_to(ROOT)
            if _private_module(rel):
                continue
            n, found = unannotated(p.read_text(), rel.as_posix())
            total += n
            missing += found
    return total, missing


def coverage_line(total: int, missing: list[str]) -> str:
    done = total - len(missing)
    return f"public functions fully annotated: {done} of {total} ({100 * done / total:.1f} %)"


def test_the_counter_finds_what_lacks_an_annotation():
    src = '''
def f(a: int) -> int: ...
def g(a, b: int) -> int: ...
def h(a: int): ...
def _private(a): ...
class C:
    def m(self, x: int) -> None: ...
    def n(self, x) -> None: ...
    @staticmethod
    def s(x) -> None: ...
    @classmethod
    def c(cls) -> None: ...
    def _hidden(self, x): ...
    class Inner:
        def i(self, y): ...
class _P:
    def m(self, x): ...
'''
    total, found = unannotated(src, "m.py")
    assert total == 8
    assert found == ["m.py:g", "m.py:h", "m.py:C.n", "m.py:C.s", "m.py:C.Inner.i"]


def test_every_public_function_is_annotated():
    total, missing = survey()
    print(coverage_line(total, missing))
    new = sorted(set(missing) - NOT_YET_ANNOTATED)
    assert not new, "public functions without a full annotation (annotate every parameter and the return):\n" + \
        "\n".join(new)
    stale = sorted(NOT_YET_ANNOTATED - set(missing))
    assert not stale, f"these are annotated now (or gone): take them off NOT_YET_ANNOTATED: {stale}"


if __name__ == "__main__":
    total, missing = survey()
    print("\n".join(missing))
    print(coverage_line(total, missing))
    sys.exit(0)
