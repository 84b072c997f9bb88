"""The ``testbed`` command line: one subcommand per job.

Subcommands live in their own modules and are imported only when used, so
``testbed simulate`` does not pay for Zenoh, MCAP or Rerun.  A module exposes
``add_arguments(parser)`` and ``main(args) -> int``.

Exit codes of every command: 0 ok, 1 the run or job failed, 2 bad input
(``testbed.common.errors.BadInput``: one line on stderr, never a traceback).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys

from .common.dispatch import (
    CHILD_COMMANDS,
    EPILOG,
    QUIET_START,
    add_command_arguments,
    run_command,
    run_guarded,
    runner_of,
)

__all__ = ["COMMANDS", "QUIET_START", "build_parser", "main", "run_guarded"]

DESCRIPTION = ("Real-time testbed for quantized control of nonlinear plants under DoS attacks. "
               "Run 'testbed COMMAND --help' for a command's options.")

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("testbed.commands.simulate", "run a scenario in the in-process simulator"),
    "scenarios": ("testbed.commands.simulate", "list the bundled scenarios"),
    "secret": ("testbed.commands.secret", "write a new credentials file for nodes started by hand"),
    "plants": ("testbed.commands.plants", "list the built-in and installed plants"),
    "check-plant": ("testbed.commands.plants", "check a plant: shapes, f(0, 0), A, B, L, Assumption 2"),
    "methods": ("testbed.commands.methods", "list the coding-and-control methods (bundled and installed)"),
    "versus": ("testbed.commands.methods", "methods head to head on the same attack realizations"),
}


def _module_exists(module: str) -> bool:
    """Whether ``module`` can be imported, without importing it or its parent packages.

    ``importlib.util.find_spec("a.b.c")`` imports ``a.b`` first: here that would load
    ``testbed.analysis`` (scipy.optimize and more) into every process, live nodes included.
    """
    parts = module.split(".")
    if parts[0] != __package__:
        return importlib.util.find_spec(module) is not None
    base = os.path.join(os.path.dirname(os.path.abspath(__file__)), *parts[1:])
    return os.path.isfile(base + ".py") or os.path.isfile(os.path.join(base, "__init__.py"))


def _optional(name: str, module: str, help_: str) -> None:
    if _module_exists(module):
        COMMANDS[name] = (module, help_)


# commands provided by the other parts of the product (present once they exist)
for _name, _mod, _help in [
    ("analyze", "testbed.commands.analyze", "Theorem 1 and 2 bounds for a scenario"),
    ("roa", "testbed.commands.analyze", "nominal region of attraction on a grid"),
    ("sweep", "testbed.commands.search", "empirical DoS tolerance over (rho_F, rho_D)"),
    ("noise", "testbed.commands.noise", "E_min against sensor noise: saturations and the ball, swept"),
    ("worst-attack", "testbed.commands.search", "the shortest DoS that drives the loop out of the region of attraction"),
    ("vulnerability", "testbed.commands.search", "that least DoS duration over the region of attraction (heat map)"),
    ("campaign", "testbed.commands.campaign", "many runs (the product of axes over a scenario) in one table, resumable"),
    ("run", "testbed.commands.run", "run a scenario live: four processes over Zenoh"),
    ("conformance", "testbed.commands.conformance", "check a node from outside against the protocol and the simulator"),
    *((name, module, help_) for name, (module, help_) in CHILD_COMMANDS.items()),
    ("report", "testbed.commands.report", "post-mortem of a recording"),
    ("resimulate", "testbed.commands.resimulate", "re-run a recording in the simulator and compare, sample by sample"),
    ("vectors", "testbed.commands.vectors", "test vectors for a node implemented elsewhere: phi_T and each role's messages"),
    ("replay", "testbed.commands.replay", "open a recording in Rerun"),
    ("export", "testbed.commands.export", "a recording as Parquet or CSV, one row per sample"),
    ("compare", "testbed.commands.compare", "two runs (recordings or scenarios) compared sample by sample"),
]:
    try:
        _optional(_name, _mod, _help)
    except ModuleNotFoundError:
        pass


def _version() -> str:
    from . import __version__

    return f"testbed (dos-testbed) {__version__}"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="testbed", description=DESCRIPTION, epilog=EPILOG)
    ap.add_argument("--version", action="version", version=_version())
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_, epilog=EPILOG)
        add_command_arguments(p, importlib.import_module(module), name)
        p.set_defaults(_module=module, _name=name)
    return ap


#: commands that end their process straight after the result is out, without the interpreter's
#: teardown (unloading numba's compiled kernels and registries takes 0.15 to 0.3 s): ``testbed run``
FAST_EXIT = {"run"}


#: ... and the post-mortems of a recording, which first run the exit handlers (``atexit``: logging's, temporary
#: files'), when no other thread of theirs is left to finish: their output is written and closed by then
FAST_EXIT_AFTER_HANDLERS = {"report", "export", "compare", "resimulate"}


def _only_daemon_threads() -> bool:
    import threading

    return all(t.daemon or t is threading.main_thread() for t in threading.enumerate())


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the process's own command line: it ends with the command
        name = sys.argv[1] if sys.argv[1:2] else ""
        if name in FAST_EXIT_AFTER_HANDLERS:  # their own process: fewer passes of the collector (common.gcpasses)
            from .common import gcpasses

            gcpasses.raise_threshold()
            # ... and one BLAS thread (set before numpy loads; the user's own setting wins): the two OpenBLAS
            # copies that numpy and scipy (through numba) load start a pool each, whose threads spin when they
            # start, about 0.3 s of CPU on the core the read-ahead decompresses on; a post-mortem multiplies no
            # large matrices (docs/benchmarks.md, "Post-mortems against the disk")
            os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        code = _main(sys.argv[1:])
        if name in FAST_EXIT or (name in FAST_EXIT_AFTER_HANDLERS and _only_daemon_threads()):
            if name in FAST_EXIT_AFTER_HANDLERS:
                import atexit

                atexit._run_exitfuncs()
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            os._exit(code)
        return code
    return _main(argv)


def _main(argv: list[str]) -> int:
    # build only the parser of the requested command when possible (fast start)
    if argv and argv[0] in ("--version", "-V"):
        print(_version())
        return 0
    if argv and argv[0] in COMMANDS:
        module, help_ = COMMANDS[argv[0]]
        return run_command(module, argv[0], argv[1:], help_)
    ap = build_parser()
    args = ap.parse_args(argv)
    runner = runner_of(importlib.import_module(args._module), args._name)
    return run_guarded(runner, args, f"testbed {getattr(args, '_name', None) or argv[0]}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
