"""Running one command of the ``testbed`` program: its parser, its runner, bad input as one line.

``testbed.cli`` dispatches to a command's module through ``run_command``; the launcher's forked
node children call the same function, so a child never reaches up into the command line's module.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable
from types import ModuleType

from .errors import EPILOG

#: commands that compile nothing (or must start fast): no numba listener (``testbed.common.compilenotice``)
QUIET_START = {"scenarios", "secret", "plants", "node", "record", "run", "methods"}

#: the commands that a live run's launcher starts as its children: command -> (module, one-line help)
CHILD_COMMANDS: dict[str, tuple[str, str]] = {
    "node": ("testbed.commands.node", "run one node of a live run"),
    "record": ("testbed.commands.record", "record a live run to MCAP (testbed run starts one itself)"),
}


def ident(name: str) -> str:
    """A command's name in its module's function names (worst-attack -> worst_attack)."""
    return name.replace("-", "_")


def add_command_arguments(parser: argparse.ArgumentParser, mod: ModuleType, name: str) -> None:
    """The arguments of command ``name`` of module ``mod`` (``add_arguments_NAME`` or ``add_arguments``)."""
    adder = getattr(mod, f"add_arguments_{ident(name)}", None) or mod.add_arguments
    adder(parser)


def runner_of(mod: ModuleType, name: str) -> Callable[[argparse.Namespace], int | None]:
    """The function that runs command ``name`` of module ``mod`` (``main_NAME`` or ``main``)."""
    return getattr(mod, f"main_{ident(name)}", None) or mod.main


def run_command(module: str, name: str, argv: list[str], help_: str = "") -> int:
    """``testbed NAME ARGV...``: parse ``argv`` (without the name) with the module's parser and run it guarded."""
    mod = importlib.import_module(module)
    ap = argparse.ArgumentParser(prog=f"testbed {name}", description=help_ or None, epilog=EPILOG)
    add_command_arguments(ap, mod, name)
    args = ap.parse_args(argv)
    return run_guarded(runner_of(mod, name), args, f"testbed {name}")


def run_child(argv: list[str]) -> int:
    """``testbed node ...`` or ``testbed record ...`` (``argv`` starts with the command) in this process."""
    module, help_ = CHILD_COMMANDS[argv[0]]
    return run_command(module, argv[0], argv[1:], help_)


def run_guarded(runner: Callable[[argparse.Namespace], int | None], args: argparse.Namespace, prog: str) -> int:
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
    except Exception as e:  # one line, not a traceback; the variable shows it
        refs = sys.modules.get("plants.refs")  # loaded whenever its error was raised (not imported here: start-up)
        if refs is not None and isinstance(e, refs.CodeNotTrusted):  # code stored in a file, not run: bad input
            print(f"{prog}: {e}", file=sys.stderr)
            return 2
        if os.environ.get("TESTBED_TRACEBACK"):
            raise
        print(f"{prog}: internal error: {type(e).__name__}: {e} (set TESTBED_TRACEBACK=1 for the traceback)",
              file=sys.stderr)
        return 1
