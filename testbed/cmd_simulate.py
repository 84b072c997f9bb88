"""``testbed simulate SCENARIO [--json]`` and ``testbed scenarios``."""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments_simulate(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario file (.toml) or bundled name (see 'testbed scenarios')")
    p.add_argument("--json", action="store_true", help="print one JSON object with every sample")
    p.add_argument("--duration", type=float, help="override [run] duration (seconds)")
    p.add_argument("--mode", choices=["ideal", "resilient"], help="override [quantizer] mode")


def main_simulate(args) -> int:
    import dataclasses

    from . import scenario
    from .simulate import simulate_scenario, summarize

    sc = scenario.load(args.scenario)
    if args.mode:
        sc = dataclasses.replace(sc, quantizer=dataclasses.replace(sc.quantizer, mode=args.mode))
    if args.duration:
        sc = dataclasses.replace(sc, run=dataclasses.replace(sc.run, duration=args.duration))
    res = simulate_scenario(sc)
    out = summarize(sc, res)
    if args.json:
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
    else:
        verdict = "converged" if out["converged"] else ("ESCAPED" if out["escaped"] else "not converged")
        print(f"scenario {out['scenario']}: plant {out['plant']} (n={out['n']}), T={out['T']}, M={out['M']}, "
              f"Lambda={out['Lambda']:.4f}, {out['bits']} bits/symbol, quantizer {out['mode']}")
        print(f"  K = {out['K']}")
        print(f"  {len(out['t'])} samples, {out['packets_dropped']} dropped in {len(out['dos_intervals'])} "
              f"DoS intervals, {out['saturations']} saturations, encoder/decoder agree: "
              f"{out['encoder_decoder_agree']}")
        print(f"  final ||x||_inf = {out['final_norm']:.3e} -> {verdict}"
              + (f" (flow diverged at sample {out['diverged_at']})" if out["diverged"] else ""))
    return 0


def add_arguments_scenarios(p: argparse.ArgumentParser) -> None:
    pass


def main_scenarios(args) -> int:
    from . import scenario

    for name in scenario.bundled_names():
        sc = scenario.load(name)
        print(f"{name:16s} plant={sc.plant.name:9s} T={sc.T:<6g} M={sc.quantizer.M} attack={sc.attack.kind}")
    return 0
