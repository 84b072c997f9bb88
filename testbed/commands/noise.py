"""``testbed noise SCENARIO``: the paper's quantizer (or a scenario's method) under a noisy sensor,
swept over the noise's scale and E_min (testbed.analysis.noise; docs/plants-and-quantizer.md).

    testbed noise SCENARIO [--scale S ...] [--ratio R ...] [--distribution uniform|normal] [--seed N]
                           [--settle SECONDS] [--method NAME] [--plot PATH.png] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from ..common import cliargs
from ..record.tracereader import read_recording_trace

SCALES = (1e-6, 1e-5, 1e-4)
RATIOS = (0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, 8.0, 12.0, 20.0)


def _nonneg(v: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{v!r} is not a number") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"{v!r}: must be a finite number >= 0")
    return x


def _positive(v: str) -> float:
    x = _nonneg(v)
    if x == 0:
        raise argparse.ArgumentTypeError(f"{v!r}: must be > 0")
    return x


def add_arguments(p: argparse.ArgumentParser) -> None:
    cliargs.add_scenario(p)
    p.add_argument("--scale", type=_positive, nargs="+", default=list(SCALES), metavar="S",
                   help="sensor noise scales (uniform: half-width; normal: sigma); default "
                        + " ".join(f"{s:g}" for s in SCALES))
    p.add_argument("--ratio", type=_nonneg, nargs="+", default=list(RATIOS), metavar="R",
                   help="E_min = R b for each R (b: the noise's bound, the uniform scale or 4 sigma, plus half an "
                        "ADC step); default " + " ".join(f"{r:g}" for r in RATIOS))
    p.add_argument("--distribution", choices=["uniform", "normal"], default="uniform", help="the noise (default uniform)")
    p.add_argument("--seed", type=int, default=1, help="the noise's seed (default 1)")
    p.add_argument("--settle", type=_nonneg, metavar="SECONDS",
                   help="count saturations and ||x|| from this time on (default: three quarters of the run)")
    p.add_argument("--method", help="the coding-and-control method (default: the scenario's)")
    cliargs.add_json(p, "every run of the sweep and the E_min relation per scale")
    cliargs.add_plot(p, "draw the recaptures and the steady ||x|| over E_min / b")
    cliargs.add_no_progress(p)


def main(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..analysis import noise
    from ..common.errors import BadInput
    from ..common.progress import Progress

    sc = scenario.load(args.scenario, read_recording_trace=read_recording_trace)
    if args.method:
        sc = scenario.with_overrides(sc, {"method": args.method})
    if args.settle is not None and args.settle >= sc.run.duration:
        raise BadInput(f"--settle {args.settle:g} s is not before the end of the run ({sc.run.duration:g} s)")
    prog = Progress("noise sweep", enabled=not args.no_progress and not args.json)
    data = noise.sweep(sc, args.scale, args.ratio, distribution=args.distribution, seed=args.seed,
                       settle=args.settle, progress=prog)
    if args.plot:
        noise.plot_sweep(data, args.plot, size=args.figsize)
        data["figure"] = str(args.plot)
    if args.json:
        sys.stdout.write(json.dumps(data) + "\n")
        return 0
    print(f"scenario {data['scenario']}: M = {data['M']}, Lambda = {data['Lambda']:.4g}, linearized growth "
          f"||e^(A T)||_inf = {data['growth']:.4g}; {data['distribution']} sensor noise, seed {data['seed']}; "
          f"steady from {data['settle_s']:g} s")
    for e in data["scales"]:
        print(f"  scale {e['scale']:g} (bound b = {e['b']:g}): E_min estimate {e['E_min_estimate']:.3g} "
              f"({e['E_min_estimate'] / e['b']:.3g} b), guarantee {e['E_min_guarantee']:.3g} "
              f"({e['E_min_guarantee'] / e['b']:.3g} b)")
        print("      E_min/b      E_min   saturations (steady)   max|x| steady       ball   outcome")
        for r in e["runs"]:
            out = "ESCAPED" if r["escaped"] else ("in the ball" if r["inside_ball"] else "outside the ball")
            print(f"    {r['ratio']:9.3g} {r['E_min']:10.3g} {r['saturations']:8d} ({r['saturations_after']:4d})"
                  f"       {r['tail_norm']:11.3g} {r['ball']:10.3g}   {out}")
    if args.plot:
        print(f"  figure: {args.plot}")
    return 0
