"""The ``testbed`` command line: one subcommand per job.

Subcommands live in their own modules and are imported only when used, so
``testbed simulate`` does not pay for Zenoh, MCAP or Rerun.  A module exposes
``add_arguments(parser)`` and ``main(args) -> int``.

Exit codes of every command: 0 ok, 1 the run or job failed, 2 bad input
(``testbed.errors.BadInput``: one line on stderr, never a traceback).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

DESCRIPTION = ("Real-time testbed for quantized control of nonlinear plants under DoS attacks. "
               "Run 'testbed COMMAND --help' for a command's options.")
EPILOG = "exit codes: 0 ok, 1 the run or job failed, 2 bad input"

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("testbed.cmd_simulate", "run a scenario in the in-process simulator"),
    "scenarios": ("testbed.cmd_simulate", "list the bundled scenarios"),
    "secret": ("testbed.cmd_secret", "write a new credentials file for nodes started by hand"),
    "plants": ("testbed.cmd_plants", "list the built-in and installed plants"),
    "check-plant": ("testbed.cmd_plants", "check a plant: shapes, f(0, 0), A, B, L, Assumption 2"),
    "methods": ("testbed.cmd_methods", "list the coding-and-control methods (bundled and installed)"),
    "versus": ("testbed.cmd_methods", "methods head to head on the same attack realizations"),
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
    ("analyze", "testbed.analysis.cli", "Theorem 1 and 2 bounds for a scenario"),
    ("roa", "testbed.analysis.cli", "nominal region of attraction on a grid"),
    ("sweep", "testbed.analysis.cli", "empirical DoS tolerance over (rho_F, rho_D)"),
    ("worst-attack", "testbed.analysis.cli", "the shortest DoS that drives the loop out of the region of attraction"),
    ("vulnerability", "testbed.analysis.cli", "that least DoS duration over the region of attraction (heat map)"),
    ("run", "testbed.launcher", "run a scenario live: four processes over Zenoh"),
    ("node", "testbed.nodes.main", "run one node of a live run"),
    ("record", "testbed.nodes.recorder", "record a live run to MCAP (testbed run starts one itself)"),
    ("report", "testbed.report", "post-mortem of a recording"),
    ("resimulate", "testbed.resimulate", "re-run a recording in the simulator and compare, sample by sample"),
    ("replay", "testbed.io.viewer", "open a recording in Rerun"),
    ("export", "testbed.export", "a recording as Parquet or CSV, one row per sample"),
    ("compare", "testbed.compare", "two runs (recordings or scenarios) compared sample by sample"),
]:
    try:
        _optional(_name, _mod, _help)
    except ModuleNotFoundError:
        pass


def _ident(name: str) -> str:
    """A command's name in its module's function names (worst-attack -> worst_attack)."""
    return name.replace("-", "_")


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
        mod = importlib.import_module(module)
        adder = getattr(mod, f"add_arguments_{_ident(name)}", None) or getattr(mod, "add_arguments")
        adder(p)
        p.set_defaults(_module=module, _name=name)
    return ap


#: commands that compile nothing (or must start fast): no numba listener (``testbed.compilenotice``)
QUIET_START = {"scenarios", "secret", "plants", "node", "record", "run", "methods"}


#: commands that end their process straight after the result is out, without the interpreter's
#: teardown (unloading numba's compiled kernels takes about 0.3 s): ``testbed run``
FAST_EXIT = {"run"}


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the process's own command line: it ends with the command
        code = _main(sys.argv[1:])
        if sys.argv[1:2] and sys.argv[1] in FAST_EXIT:
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
        name = argv[0]
        module, help_ = COMMANDS[name]
        mod = importlib.import_module(module)
        ap = argparse.ArgumentParser(prog=f"testbed {name}", description=help_, epilog=EPILOG)
        adder = getattr(mod, f"add_arguments_{_ident(name)}", None) or getattr(mod, "add_arguments")
        adder(ap)
        args = ap.parse_args(argv[1:])
        runner = getattr(mod, f"main_{_ident(name)}", None) or getattr(mod, "main")
    else:
        ap = build_parser()
        args = ap.parse_args(argv)
        mod = importlib.import_module(args._module)
        runner = getattr(mod, f"main_{_ident(args._name)}", None) or getattr(mod, "main")
    return run_guarded(runner, args, f"testbed {getattr(args, '_name', None) or argv[0]}")


def run_guarded(runner, args, prog: str) -> int:
    """Run a command: bad input is one line and exit 2, an internal error one line and exit 1.

    ``TESTBED_TRACEBACK=1`` re-raises instead (for bug reports).
    """
    from .errors import BadInput

    if prog.split()[-1] not in QUIET_START:
        from . import compilenotice

        compilenotice.install()
    try:
        return int(runner(args) or 0)
    except BadInput as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as e:
        print(f"{prog}: {e.strerror or e}: {e.filename}" if getattr(e, "filename", None) else f"{prog}: {e}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into head & co.
        sys.stderr.close()
        return 0
    except Exception as e:  # noqa: BLE001 - one line, not a traceback; the variable shows it
        if os.environ.get("TESTBED_TRACEBACK"):
            raise
        print(f"{prog}: internal error: {type(e).__name__}: {e} (set TESTBED_TRACEBACK=1 for the traceback)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
