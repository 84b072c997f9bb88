"""``testbed conformance ROLE SCENARIO [--json] -- COMMAND [ARGS...]``: check a node from outside against the
spec and the simulator, requirement by requirement (``testbed.live.conformance``)."""

from __future__ import annotations

import argparse
import json
import math
import os
import secrets
import shutil
import sys
import tempfile
from pathlib import Path

from ..common import cliargs, optionspec
from ..live.conformance import PLANT_TOLERANCE
from ..nodes.options import RunConfig, add_run_option_arguments
from ..record.tracereader import read_recording_trace
from ..wire import transport
from ..wire.session import add_network_arguments


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("role", choices=transport.ROLES, help="the role COMMAND plays")
    p.add_argument("scenario", help="scenario file (.toml) or bundled name")
    p.add_argument("command", nargs=argparse.REMAINDER, metavar="[OPTIONS] -- COMMAND [ARGS...]",
                   help="the node to check, started with TESTBED_JOIN set (e.g. -- testbed node plant)")
    _add_options(p)


def _add_options(p: argparse.ArgumentParser) -> None:
    cliargs.add_json(p, "the verdict: passed (over the required requirements), and requirements (name, required, "
                        "passed, status, detail)")
    add_run_option_arguments(p)
    add_network_arguments(p.add_argument_group("network (as testbed run's)"), command="conformance")
    g = p.add_argument_group("conformance")
    g.add_argument("--bit-exact", action="store_true",
                   help="ROLE plant: require equals_simulator (the plant equals the testbed's own bit for bit) "
                        "instead of loop_equals_replay and plant_follows_model (a device's judgement, the default)")
    g.add_argument("--plant-tolerance", type=float, default=PLANT_TOLERANCE, metavar="E",
                   help="ROLE plant: plant_follows_model passes when max_k ||x_k+1 - phi_T(x_k, u_k)||_inf <= E "
                        "(default %(default)g)")
    g.add_argument("--keep", metavar="DIR", help="keep the recordings and logs in DIR (default: a temporary folder, "
                                                "kept when a requirement is not met)")
    optionspec.add_arguments(p, RunConfig, "conformance", group=g, names=("startup_timeout",))
    g.add_argument("--no-adverse", action="store_true",
                   help="do not feed the node a late, a duplicated and an invalid message (the adverse cases)")
    g.add_argument("--timeout", type=float, default=300.0, metavar="S", help="give up on a run after S seconds "
                                                                              "(default %(default)s)")


def replay_on_recorded_plant(path: str) -> dict:
    """The conformance run's recording re-run on the recorded plant (``testbed resimulate --plant recorded
    --json``): what ``loop_equals_replay``, ``plant_follows_model`` and the loop's nodes' adverse cases read.
    The recording is the one this command just made of the user's scenario: its code is trusted."""
    from ..runs.resimulate import resimulation
    from ..runs.run import open as open_run

    return resimulation(open_run(path, trust_code=True), plant="recorded")


def main(args: argparse.Namespace) -> int:
    from ..common.errors import BadInput
    from ..live.conformance import ADVERSE, DEVICE, REQUIREMENTS, conformance, feedable
    from .liveconfig import run_options, session_options

    # the options after SCENARIO, then -- COMMAND [ARGS...] (argparse drops a -- that directly follows SCENARIO)
    rest = list(args.command)
    if "--" not in rest and rest[:1] and rest[0].startswith("-"):
        raise BadInput("put -- before COMMAND: testbed conformance ROLE SCENARIO [OPTIONS] -- COMMAND [ARGS...]")
    cut = rest.index("--") if "--" in rest else -1
    own = argparse.ArgumentParser(prog="testbed conformance ROLE SCENARIO")
    _add_options(own)
    own.parse_args(rest[:cut], namespace=args)
    command = rest[cut + 1:]
    if not command:
        raise BadInput("no COMMAND: testbed conformance ROLE SCENARIO -- COMMAND [ARGS...]")
    if shutil.which(command[0]) is None and not os.path.exists(command[0]):
        raise BadInput(f"{command[0]}: no such command")
    from .. import scenario

    # a bad scenario: one line, exit 2, before anything runs
    scenario.load(args.scenario, read_recording_trace=read_recording_trace)
    opts = run_options(args, "conformance")
    if opts.colocate:
        raise BadInput("--colocate: an external node runs alone in its process")
    net = session_options(args, "conformance")  # testbed run's session, as the launcher takes it
    if not args.no_adverse and feedable(net):
        raise BadInput(feedable(net))
    if not (args.plant_tolerance >= 0 and math.isfinite(args.plant_tolerance)):
        raise BadInput(f"--plant-tolerance {args.plant_tolerance!r}: not a finite number >= 0")
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="testbed-conformance-"))
    run_id = args.run_id or f"conformance-{args.role}-{os.getpid()}-{secrets.token_hex(3)}"
    res = conformance(args.role, args.scenario, command, folder=folder, run_id=run_id, flags=opts.cli(),
                      timeout=args.timeout, startup_timeout=args.startup_timeout, feed=not args.no_adverse,
                      session=net, bit_exact=args.bit_exact, plant_tolerance=args.plant_tolerance,
                      replay=replay_on_recorded_plant)
    if not args.keep and res["passed"]:
        shutil.rmtree(folder, ignore_errors=True)
    else:
        res["folder"] = str(folder)
    if args.json:
        json.dump(res, sys.stdout)
        sys.stdout.write("\n")
    else:
        width = max(len(n) for n in (*REQUIREMENTS, *DEVICE, *ADVERSE))
        print(f"conformance of the {args.role} {' '.join(command)!r} on {args.scenario}: "
              + ("PASSED" if res["passed"] else "NOT PASSED"))
        for q in res["requirements"]:
            print(f"  {q['status'].upper():12s} {q['name']:{width}s}  "
                  + ("" if q["required"] else "(not required) ") + q["detail"])
        if res.get("folder"):
            print(f"  recordings and logs: {res['folder']}")
    return 0 if res["passed"] else 1
