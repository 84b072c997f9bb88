"""``testbed record SCENARIO``: record a live run to MCAP (``testbed.nodes.recorder``), its flags.

``testbed run`` starts its recorder with these flags (``RecorderConfig.argv``)."""

from __future__ import annotations

import argparse

from ..nodes.options import add_run_option_arguments
from ..wire.session import add_zenoh_arguments
from .liveconfig import recorder_config


def add_arguments_record(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="the run's scenario (file or bundled name): stored in the recording")
    p.add_argument("--out", metavar="PATH.mcap",
                   help="recording file (default recordings/<scenario>-<UTC start>-<run id>.mcap); never overwritten")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.add_argument("--loop", choices=["auto", "on", "off"], default="auto",
                   help="record the control-path messages too (auto: when T >= 10 ms; default %(default)s)")
    p.add_argument("--flush", type=float, default=0.5, metavar="S",
                   help="flush the file at least every S seconds (what a SIGKILL can lose; default %(default)s)")
    p.add_argument("--linger", type=float, default=2.0, metavar="S",
                   help="standalone: stop S seconds after the plant's Stop (default %(default)s)")
    p.add_argument("--nice", type=int, default=10, metavar="N",
                   help="run at this nice value so the loop's nodes go first on a busy machine (default %(default)s)")
    p.add_argument("--cpus", metavar="LIST", help="pin the recorder to these CPUs, e.g. 6 or 6,7")
    p.add_argument("--parent-pid", type=int, help=argparse.SUPPRESS)
    p.add_argument("--launched", action="store_true", help=argparse.SUPPRESS)  # by testbed run
    p.add_argument("--scenario-ref", help=argparse.SUPPRESS)
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO (start-up, every event)")
    add_run_option_arguments(p)
    add_zenoh_arguments(p)


def main_record(args) -> int:
    from ..nodes.recorder import run_recorder

    return run_recorder(recorder_config(args))
