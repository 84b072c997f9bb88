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
    p.add_argument("--T", type=float, metavar="SECONDS", help="override [quantizer] T, the sample period")
    p.add_argument("--out", metavar="PATH.mcap",
                   help="also write the run as an MCAP recording (the topics of a live run; see testbed report)")
    p.add_argument("--rrd", metavar="PATH.rrd", help="also write a Rerun recording of the run (see testbed replay)")


def main_simulate(args) -> int:
    from . import scenario
    from .simulate import simulate_scenario, summarize

    overrides = {"mode": args.mode, "duration": args.duration, "T": args.T}
    sc = scenario.with_overrides(scenario.load(args.scenario), overrides)
    res = simulate_scenario(sc)
    out = summarize(sc, res)
    if args.out:
        from .io.recording import record_simulation

        record_simulation(args.out, sc, res, overrides={k: v for k, v in overrides.items() if v is not None},
                          ref=args.scenario)
    if args.rrd:
        from .io.viewer import simulation_to_rrd

        simulation_to_rrd(args.rrd, sc, res)
    if args.json:
        sys.stdout.write(json.dumps(out))  # the C encoder in one go: 2x json.dump on long runs
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
        if args.out:
            print(f"  recording: {args.out}")
        if args.rrd:
            print(f"  rerun recording: {args.rrd}")
    return 0


def add_arguments_scenarios(p: argparse.ArgumentParser) -> None:
    pass


def main_scenarios(args) -> int:
    from . import scenario

    for name in scenario.bundled_names():
        sc = scenario.load(name)
        print(f"{name:16s} plant={sc.plant.name:9s} T={sc.T:<6g} M={sc.quantizer.M} attack={sc.attack.kind}")
    return 0
