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
NOT_YET_ANNOTATED: set[str] = {
    "testbed/campaign/batch.py:batch_key",
    "testbed/campaign/code.py:changed",
    "testbed/campaign/code.py:collect",
    "testbed/campaign/code.py:write_copies",
    "testbed/campaign/engine.py:Point.scenario",
    "testbed/campaign/engine.py:attack_seed",
    "testbed/campaign/engine.py:run_point",
    "testbed/campaign/engine.py:run_points",
    "testbed/campaign/engine.py:seeds_for",
    "testbed/campaign/engine.py:settle_samples",
    "testbed/campaign/engine.py:simulate_one",
    "testbed/campaign/folder.py:manifest",
    "testbed/campaign/folder.py:prepare",
    "testbed/campaign/runner.py:plot",
    "testbed/campaign/runner.py:run",
    "testbed/campaign/runner.py:verify",
    "testbed/campaign/spec.py:PlannedRun.scenario",
    "testbed/campaign/spec.py:base_scenario",
    "testbed/campaign/spec.py:plan",
    "testbed/campaign/tables.py:fmt_ci",
    "testbed/campaign/tables.py:fmt_p",
    "testbed/commands/analyze.py:figure_paths",
    "testbed/commands/analyze.py:is_paper_example",
    "testbed/commands/analyze.py:not_modelled",
    "testbed/commands/analyze.py:note_not_modelled",
    "testbed/commands/analyze.py:plant_and_model",
    "testbed/commands/analyze.py:true_plant",
    "testbed/commands/liveconfig.py:node_config",
    "testbed/commands/liveconfig.py:recorder_config",
    "testbed/commands/liveconfig.py:run_config",
    "testbed/commands/liveconfig.py:run_options",
    "testbed/commands/liveconfig.py:session_options",
    "testbed/commands/simulate.py:recorded_latency",
    "testbed/runs/compare.py:compare",
    "testbed/runs/compare.py:load_pair",
    "testbed/runs/compare.py:load_side",
    "testbed/runs/compare.py:plot",
    "testbed/runs/export.py:export",
    "testbed/runs/export.py:table",
    "testbed/runs/report.py:losses_as_dos",
    "testbed/runs/report.py:plot",
    "testbed/runs/report.py:recording_end",
    "testbed/runs/report.py:report",
    "testbed/runs/report.py:report_of_run",
    "testbed/runs/report.py:run_of",
    "testbed/runs/report.py:telemetry_check",
    "testbed/runs/resimulate.py:kernel_replay",
    "testbed/runs/resimulate.py:loop_differences",
    "testbed/runs/resimulate.py:plant_model_error",
    "testbed/runs/resimulate.py:recorded_run",
    "testbed/runs/resimulate.py:resimulation",
    "testbed/runs/run.py:Run.recorded_columns",
    "testbed/runs/run.py:Run.to_pandas",
    "testbed/runs/run.py:Run.to_polars",
    "testbed/runs/run.py:resimulate",
    "testbed/runs/run.py:resolve_scenario",
    "testbed/runs/run.py:run_of_recording",
    "testbed/runs/run.py:run_of_simulation",
    "testbed/runs/run.py:simulate",
    "testbed/scenario/rulesofthumb.py:disturbance_bound",
    "testbed/scenario/rulesofthumb.py:growth",
    "testbed/scenario/rulesofthumb.py:warnings",
    "testbed/scenario/write.py:with_attack",
}


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
