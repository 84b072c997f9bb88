"""``testbed replay RUN.mcap [--rrd PATH] [--spawn]``: a recording opened in Rerun."""

from __future__ import annotations

import argparse
import json

from ..common import cliargs
from ..runs.run import open as open_run
from ..view.rerun import run_to_rrd


def add_arguments_replay(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an MCAP recording (testbed run --out, testbed simulate --out)")
    cliargs.add_rrd(p, "write the view to this file")
    p.add_argument("--spawn", action="store_true", help="open it in a Rerun viewer (the default without --rrd)")
    cliargs.add_no_roa(p)
    cliargs.add_json(p, "what was written (the .rrd path, the run id, the number of samples)")
    cliargs.add_trust_code(p)


def main_replay(args: argparse.Namespace) -> int:
    run = open_run(args.recording, trust_code=args.trust_code)
    s, sc = run.summary, run.scenario
    spawn = args.spawn or not args.rrd
    roa = not args.no_roa and not sc.code_not_run()  # the region needs the model's code
    run_to_rrd(args.rrd, run, recording_id=str(s.get("run_id") or sc.name), roa=roa, spawn=spawn)
    if args.json:
        print(json.dumps({"rrd": args.rrd, "spawned": spawn, "run_id": s.get("run_id"), "samples": s.get("samples"),
                          "scenario": sc.name}))
    elif args.rrd:
        print(f"rerun recording: {args.rrd} (open with: rerun {args.rrd})")
    return 0
