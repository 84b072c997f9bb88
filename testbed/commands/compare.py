"""``testbed compare A B [--json] [--plot PATH]``: two runs compared sample by sample.

Its arguments and text output; the comparison itself is ``testbed.runs.compare``.
"""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from ..common import cliargs
from ..runs.compare import (
    compare,
    load_pair,
    plot,
)

if TYPE_CHECKING:
    from ..runs.run import Run


def _name(run: Run) -> str:
    """A run as a figure names it: its scenario and where it came from (not a file path)."""
    kind = {"live": "live run", "simulate": "simulation"}.get(run.source, run.source)
    return f"{run.scenario.name}, {kind}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("a", help="a recording (.mcap) or a scenario (bundled name or .toml) to simulate")
    p.add_argument("b", help="the other run: a recording or a scenario (simulated with the recording's overrides)")
    cliargs.add_json(p, "the comparison")
    cliargs.add_plot(p, "draw both runs' states (A solid, B dashed), their difference and the lost samples of each, "
                        "DoS shaded")
    cliargs.add_trust_code(p, "a recording")


def main(args: argparse.Namespace) -> int:
    ra, rb = load_pair(args.a, args.b, trust_code=args.trust_code)
    c = compare(ra, rb)
    c["a"]["ref"], c["b"]["ref"] = str(args.a), str(args.b)
    if args.plot:
        plot(ra, rb, args.plot, title=f"A: {_name(ra)}; B: {_name(rb)}", size=args.figsize)
    if args.json:
        print(json.dumps(c))
    else:
        s = c["samples"]
        print(f"A {args.a} ({c['a']['source']}, {s['a']} samples) vs B {args.b} ({c['b']['source']}, "
              f"{s['b']} samples)")
        if c["identical"]:
            print("  IDENTICAL: every compared value is equal, bit for bit")
        else:
            print(f"  first divergence at k = {c['first_divergence']}; max ||x_A - x_B||_inf = "
                  f"{c['max_state_error']!s}")
            print(f"  theta differs at {c['theta_differs']} samples {c['theta_differs_at'][:10]}, symbols at "
                  f"{c['symbols_differ']} {c['symbols_differ_at'][:10]}")
            print("  first k per quantity: " + ", ".join(f"{q} {v}" for q, v in c["differs_first"].items()))
        if args.plot:
            print(f"  figure: {args.plot}")
    return 0
