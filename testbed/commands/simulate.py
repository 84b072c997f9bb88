"""``testbed simulate SCENARIO [--json]`` and ``testbed scenarios``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..common import cliargs

if TYPE_CHECKING:
    import numpy as np

    from ..scenario import Scenario


def add_arguments_simulate(p: argparse.ArgumentParser) -> None:
    from ..nodes.options import add_run_option_arguments

    cliargs.add_scenario(p)
    cliargs.add_json(p, "the run (every sample, counts and outcome)")
    add_run_option_arguments(p, title="run options (as testbed run takes them)")
    p.add_argument("--corrupt", metavar="K[:range|:length],...",
                   help="the attacker corrupts the payload of these samples (as testbed run --corrupt)")
    p.add_argument("--latency-from", metavar="RUN.mcap",
                   help="physical timing: the latency of u_k sample by sample as a recorded live run measured it "
                        "(instead of [run] sim_delay)")
    p.add_argument("--simulator", choices=["auto", "batch", "per-sample"], default="auto",
                   help="auto (default): the batch kernel where the run allows it (bundled plant and method, no "
                        "--corrupt or --ack-via-attacker), else the per-sample loop; per-sample: always the loop of "
                        "the live nodes' protocol objects (the same numbers, slower); batch: the kernel or exit 2")
    cliargs.add_out(p, "also write the run as an MCAP recording (the topics of a live run; see testbed report); "
                       "never overwritten")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    cliargs.add_rrd(p, "also write a Rerun recording of the run (see testbed replay)")
    cliargs.add_plot(p, "draw the paper's Fig. 2 (states, input, E_k at both ends, DoS shaded)")
    cliargs.add_no_roa(p)


def main_simulate(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..common.errors import BadInput
    from ..loop.channel import loss_text
    from ..nodes.attacker import parse_corrupt
    from ..record.tracereader import read_recording_trace
    from ..scenario import rulesofthumb
    from ..sim.batch import outcome_text, summarize
    from ..sim.loop import LinkEffects
    from ..sim.trajectory import simulate_scenario
    from .liveconfig import run_options

    opts = run_options(args)
    overrides = opts.overrides()
    sc = scenario.load(args.scenario, overrides=overrides, read_recording_trace=read_recording_trace)
    sc, over = scenario.with_seed(sc, overrides)
    if over != overrides:
        overrides = over
        print(f"testbed simulate: the random attack has no seed; drew seed = {over['seed']} (--seed "
              f"{over['seed']} repeats it{'; recorded' if args.out else ''})", file=sys.stderr)
    try:
        corrupt = parse_corrupt(args.corrupt)
    except ValueError as e:
        raise BadInput(str(e)) from None
    effects = LinkEffects(ack_via_attacker=opts.ack_via_attacker, corrupt=tuple(sorted(corrupt.items())))
    latency = None
    if args.latency_from:
        if sc.run.timing != "physical":
            raise BadInput("--latency-from applies to physical timing: add --timing physical")
        latency = recorded_latency(args.latency_from, sc)
    if sc.method_note:
        print(f"testbed simulate: {sc.method_note}", file=sys.stderr)
    for line in rulesofthumb.warnings(sc):  # a documented rule of thumb broken: said before the run
        print(f"testbed simulate: warning: {line}", file=sys.stderr)
    try:
        res = simulate_scenario(sc, effects=effects, latency=latency, simulator=args.simulator)
    except ValueError as e:
        if args.simulator != "batch":
            raise
        raise BadInput(f"--simulator batch: {e}") from None
    out = summarize(sc, res, arrays=not args.json)  # the text needs no per-sample lists
    if args.out:
        from ..record.recording import record_simulation

        record_simulation(args.out, sc, res, overrides={k: v for k, v in overrides.items() if v is not None},
                          ref=args.scenario, exclusive=not args.force)
    if args.rrd:
        from ..runs.run import run_of_simulation
        from ..view.rerun import run_to_rrd

        run_to_rrd(args.rrd, run_of_simulation(sc, res, summary=out), recording_id=f"sim-{sc.name}",
                   roa=not args.no_roa)
    if args.plot:
        from ..analysis.figures import figure_title, plot_time_series

        ivs = None if sc.attack.online else [list(iv) for iv in res.intervals().intervals]
        plot_time_series(res, args.plot, intervals=ivs, title=figure_title(sc), size=args.figsize)
        out["figure"] = str(args.plot)
    if args.json:
        sys.stdout.write(json.dumps(out))  # the C encoder in one go: 2x json.dump on long runs
        sys.stdout.write("\n")
    else:
        verdict = outcome_text(out)
        print(f"scenario {out['scenario']}: plant {out['plant']} (n={out['n']}), T={out['T']}, "
              + (f"M={out['M']}, Lambda={out['Lambda']:.4f}, " if out["method"] == "paper" else "")
              + f"{out['bits']} bits/symbol, method {out['method']}"
              + (f" (quantizer {out['mode']})" if out["method"] == "paper" else ""))
        print(f"  K = {out['K']}")
        if sc.plant.device is not None and args.simulator == "auto":  # the batch kernel has no device model
            print(f"  simulator: the per-sample loop (the plant is a device: {sc.plant.device.describe()})")
        if sc.model is not None and sc.model.explicit:
            print(f"  true plant {out['plant']} {out['plant_params']}; model {out['model']} {out['model_params']} "
                  "(predictions, design)")
        # every lost sample under its one cause (without a [network] every loss is the attacker's)
        ls = out.get("losses") or {"attacker": out["packets_dropped"]}
        print(f"  {len(out['t'])} samples, {out['packets_dropped']} lost ({loss_text(ls)}), "
              f"{len(out['dos_intervals'])} DoS intervals (the attacker's), {out['saturations']} saturations, "
              f"encoder/decoder agree: {out['encoder_decoder_agree']}")
        if sc.network is not None and out.get("losses"):
            print(f"  [network]: the channels' draws from seed {sc.network.seed}")
        print(f"  final ||x||_inf = {out['final_norm']:.3e} -> {verdict}")
        if args.out:
            print(f"  recording: {args.out}")
        if args.rrd:
            print(f"  rerun recording: {args.rrd}")
        if args.plot:
            print(f"  figure: {args.plot}")
    if res.plant_fault is not None:  # the true plant failed (an FMU step): the run is data, the job failed
        print(f"testbed simulate: plant fault at sample {res.plant_fault_at} (t = {res.plant_fault_at * sc.T:g} s): "
              f"{res.plant_fault}", file=sys.stderr)
        return 1
    if res.method_fault is not None:  # the method's end raised: the run ended there
        print(f"testbed simulate: {res.method_fault}", file=sys.stderr)
        return 1
    if res.lockstep_breaks:
        print(f"testbed simulate: method {sc.method.name!r} broke lockstep: its encoder and decoder disagree "
              f"from sample {res.lockstep_breaks[0]} ({len(res.lockstep_breaks)} samples)", file=sys.stderr)
        return 1
    return 0


def recorded_latency(path: str | Path, sc: Scenario) -> np.ndarray:
    """The latency [ns] of u_k per sample in a recorded run: when it reached the plant after t_k (a lost
    sample's counted from the controller's loss deadline); a sample without a record: the latest one."""
    import numpy as np

    from ..common.errors import BadInput
    from ..record import reader
    from ..wire import messages as msg

    try:
        rec = reader.read(path)
    except (OSError, ValueError) as e:
        raise BadInput(f"{path}: {e}") from None
    P = rec.telemetry.get("plant", {})
    N = sc.n_steps
    loss_ns = int(sc.timing_params[4])
    out = np.zeros(N, dtype=np.int64)
    last = 0
    for k in range(N):
        p = P.get(k)
        if p is not None and p.u_rx_ns != msg.NO_TIME and p.t_ns != msg.NO_TIME:
            last = max(0, p.u_rx_ns - p.t_ns - (loss_ns if p.theta == 1 else 0))
        out[k] = last
    return out


def add_arguments_scenarios(p: argparse.ArgumentParser) -> None:
    cliargs.add_json(p, "the list (name, description, plant, T, M, attack, duration)")
    p.add_argument("--show", metavar="NAME",
                   help="print the TOML of the bundled scenario NAME (a start for your own: "
                        "testbed scenarios --show paper > my.toml)")


def main_scenarios(args: argparse.Namespace) -> int:
    from .. import scenario
    from ..common.errors import BadInput

    if args.show:
        if args.show not in scenario.bundled_names():
            raise BadInput(f"no bundled scenario {args.show!r}; the bundled ones are "
                           f"{', '.join(scenario.bundled_names())}")
        text = scenario.load(args.show).source
        if args.json:
            print(json.dumps({"name": args.show, "toml": text}))
        else:
            sys.stdout.write(text if text.endswith("\n") else text + "\n")
        return 0

    rows = []
    for name in scenario.bundled_names():
        sc = scenario.load(name)
        rows.append({"name": name, "description": sc.description, "plant": sc.plant.name, "n": len(sc.plant.x0),
                     "T": sc.T, "M": sc.quantizer.M, "attack": sc.attack.kind, "duration": sc.run.duration})
    if args.json:
        print(json.dumps({"scenarios": rows}))
        return 0
    for r in rows:
        print(f"{r['name']:14s} {r['description']}")
        print(f"{'':14s} plant {r['plant']}, T = {r['T']:g} s, M = {r['M']}, attack {r['attack']}, "
              f"{r['duration']:g} s")
    return 0
