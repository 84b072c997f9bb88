"""``testbed resimulate RUN.mcap [--json]``: a recording re-run in the simulator, sample by sample.

Its arguments and text output; the re-run itself is ``testbed.runs.resimulate``.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..common import cliargs
from ..runs.resimulate import PLANTS
from ..runs.run import resimulate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an MCAP recording (testbed run, testbed simulate --out)")
    cliargs.add_json(p, "the comparison (samples, max_state_error, symbols_identical, E_identical, "
                        "first_divergence, ...)")
    cliargs.add_trust_code(p)
    p.add_argument("--plant", choices=PLANTS, default="auto",
                   help="what the loop is re-run on: model (the whole loop re-simulated, the plant by the scenario's "
                        "true plant), recorded (the encoder, attacker, controller and method re-run on the states the "
                        "plant reported, compared bit for bit; the plant compared step by step with the model); "
                        "auto (default): recorded when the plant was an external node or the scenario declares it a "
                        "device, else model")


def main(args: argparse.Namespace) -> int:
    from ..common.errors import BadInput

    try:
        out = resimulate(args.recording, trust_code=args.trust_code, plant=args.plant)
    except BadInput:
        raise  # it names the file already
    except (OSError, ValueError) as e:
        raise BadInput(f"{args.recording}: {e}") from None
    if args.json:
        sys.stdout.write(json.dumps(out) + "\n")
    else:
        print(f"{args.recording}: {out['samples']} samples ({out['timing_mode']} timing) {out['plant_line']} from "
              f"what the recording says happened: {out['verdict']}")
        if out["plant"] == "recorded":
            pm = out["plant_model_error"]
            print(f"  loop identical: {out['loop_identical']}; plant vs model e_k = ||x_k+1 - phi_T(x_k, u_k)||_inf: "
                  + (f"max {pm['max']:.3g} at sample {pm['at']}, mean {pm['mean']:.3g}" if pm else "not known"))
        else:
            print(f"  max ||x_k(live) - x_k(resimulated)||_inf = {out['max_state_error']:.3g}; symbols identical: "
                  f"{out['symbols_identical']}, E_k identical: {out['E_identical']}, theta_k identical: "
                  f"{out['theta_identical']}")
        r = out["replayed"]
        print(f"  replayed: {r['lost']} lost, {r['withheld']} withheld, {r['u_missing']} u_k missing"
              + (f", delays {r['delays_ns']['min'] / 1e6:.3f}..{r['delays_ns']['max'] / 1e6:.3f} ms"
                 if r["delays_ns"] else ""))
    return 0 if out["reproduced"] else 1
