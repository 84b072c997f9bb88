"""``testbed vectors SCENARIO [--n N] [--json]``: test vectors a node implemented elsewhere checks offline.

Its arguments and output; the vectors themselves are ``testbed.wire.vectors``.
"""

from __future__ import annotations

import argparse
import json

from ..common import cliargs
from ..record.tracereader import read_recording_trace


def add_arguments(p: argparse.ArgumentParser) -> None:
    cliargs.add_scenario(p)
    p.add_argument("--n", type=cliargs.int_at_least(1), default=8,
                   help="points (x, u) -> phi_T(x, u) of the flow map (default 8)")
    cliargs.add_json(p, "the vectors (flow_map: x, u, x_T, status; loop: each sample's sensor, encoder, "
                        "attacker, controller, encoder_ack and plant numbers and payloads)")


def main(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..wire.vectors import vectors

    out = vectors(scenario.load(args.scenario, read_recording_trace=read_recording_trace), n=args.n)
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"{out['scenario']}: n = {out['n']}, m = {out['m']}, T = {out['T']:g} s; flow map rtol {out['flow']['rtol']:g}, "
          f"atol {out['flow']['atol']:g}")
    for v in out["flow_map"]:
        print(f"  phi_T(x = {v['x']!r}, u = {v['u']!r}) = {v['x_T']!r}  status {v['status']}")
    for r in out["loop"]:
        e, c = r["encoder"], r["controller"]
        sym = "withheld" if e.get("withheld") else f"symbol {e['symbol']} ({e['payload']})"
        print(f"  k = {r['k']}: x {r['sensor']['x']!r} -> {sym}, "
              f"{'forwarded' if r['attacker']['forwarded'] else 'dropped'} -> theta {c['theta']}, last_rx "
              f"{c['last_rx']}, u {c['u']!r} ({c['payload']}) -> x_next {r['plant']['x_next']!r}")
    return 0
