"""The options every command shares, one name per meaning (see docs/cli.md).

==================  ===============================================================
``--json``          print the result as one JSON object on stdout
``--out PATH.mcap`` write an MCAP recording (run, simulate, record)
``--rrd PATH.rrd``  write a Rerun recording (run, simulate, replay)
``--plot PATH.png`` draw the command's figure (.png, .pdf or .svg by the extension)
``--figsize SIZE``  with --plot: ``column`` (one IEEE column) or ``page`` (two columns, default)
``--no-roa``        skip the nominal region of attraction outline (a grid computation)
``--no-progress``   no progress bars on stderr
``--workers N``     processes for batch jobs (default: every core; 1: in this process)
``--scheduler URL`` run the batch jobs on a Dask cluster instead (``tcp://HOST:PORT``)
==================  ===============================================================

Old names stay accepted as hidden aliases (``--record``, ``--rerun-no-roa``).
Exit codes: 0 ok, 1 the run or job failed, 2 bad input (``testbed.common.errors``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any, Protocol


class Arguments(Protocol):
    """What these functions add flags to: a parser or one of its argument groups."""

    def add_argument(self, *args: Any, **kwargs: Any) -> Any: ...


def add_json(p: Arguments, what: str = "the result") -> None:
    p.add_argument("--json", action="store_true", help=f"print {what} as one JSON object on stdout")


def add_out(p: Arguments, help_: str, *, aliases: tuple[str, ...] = ()) -> None:
    p.add_argument("--out", metavar="PATH.mcap", help=help_)
    for a in aliases:
        p.add_argument(a, dest="out", metavar="PATH.mcap", help=argparse.SUPPRESS)


def add_rrd(p: Arguments, help_: str) -> None:
    p.add_argument("--rrd", metavar="PATH.rrd", help=help_)


def figure_path(v: str) -> str:
    """``--plot``'s value: a path ending in .png, .pdf or .svg (the format)."""
    from .figstyle import FORMATS

    if not v.lower().endswith(FORMATS):
        raise argparse.ArgumentTypeError(f"{v!r}: a figure is written as {', '.join(FORMATS)} (by the extension)")
    return v


def add_figsize(p: Arguments) -> None:
    p.add_argument("--figsize", choices=["column", "page"], default="page",
                   help="figure width: one IEEE column (3.5 in) or both columns (7.16 in, default)")


def add_plot(p: Arguments, help_: str, *, folder: bool = False) -> None:
    """``--plot PATH`` (.png, .pdf or .svg; ``folder``: a folder too) and ``--figsize column|page``."""
    p.add_argument("--plot", metavar="PATH.png", type=None if folder else figure_path,
                   help=help_ + " (.png, .pdf or .svg by the extension)")
    add_figsize(p)


def add_no_roa(p: Arguments, *, aliases: tuple[str, ...] = ()) -> None:
    p.add_argument("--no-roa", action="store_true",
                   help="skip the nominal region of attraction outline (a grid computation of about a second)")
    for a in aliases:
        p.add_argument(a, dest="no_roa", action="store_true", help=argparse.SUPPRESS)


def add_trust_code(p: Arguments, where: str = "the recording") -> None:
    """``--trust-code``: the readers of recordings and campaign folders (docs/security.md)."""
    p.add_argument("--trust-code", action="store_true",
                   help=f"run a plant's or method's source stored in {where} when its module is not importable "
                        "here (it is code from whoever made the file; without this flag it is not run, and what "
                        "needs it, the re-simulation, is skipped)")


def add_no_progress(p: Arguments) -> None:
    p.add_argument("--no-progress", action="store_true", help="do not draw progress bars on stderr")


def add_scenario(p: Arguments) -> None:
    p.add_argument("scenario", help="scenario file (.toml) or bundled name (see 'testbed scenarios')")


def int_at_least(low: int, *, or_all: bool = False) -> Callable[[str], int | None]:
    """An argparse ``type``: an integer >= ``low``; with ``or_all`` also the word ``all`` (read as None)."""
    what = f"an integer >= {low}" + (" or 'all'" if or_all else "")

    def parse(text: str) -> int | None:
        if or_all and text == "all":
            return None
        try:
            n = int(text)
        except ValueError:
            n = None
        if n is None or n < low:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return n

    return parse


def add_workers(p: Arguments) -> None:
    p.add_argument("--workers", type=int_at_least(1), metavar="N",
                   help="worker processes for the batch simulations (default: every core; 1 runs in this "
                        "process); results are identical for every N")


def add_scheduler(p: Arguments) -> None:
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="send the batch simulations to this Dask scheduler instead of local processes "
                        "(needs the extra 'dask'; see docs/scaling.md); results are identical")


def add_batch_options(p: Arguments) -> None:
    """``--no-progress``, ``--workers``, ``--scheduler``: how an analysis command runs its batch simulations."""
    add_no_progress(p)
    add_workers(p)
    add_scheduler(p)
