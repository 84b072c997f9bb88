"""``testbed node ROLE [SCENARIO]``: one node of a live run (``testbed.nodes.main``), its flags.

``testbed run`` starts its nodes with these flags (``NodeConfig.argv``), forked or exec'd; a node started
by hand or from outside (``TESTBED_JOIN``) takes the same."""

from __future__ import annotations

import argparse

from ..nodes.inlet import RX_MODES
from ..nodes.options import add_run_option_arguments
from ..wire import transport
from ..wire.session import add_zenoh_arguments
from .liveconfig import node_config


def add_arguments_node(p: argparse.ArgumentParser) -> None:
    p.add_argument("role", choices=transport.ROLES, help="which node to run")
    p.add_argument("scenario", nargs="?",
                   help="scenario file (.toml) or bundled name; without it, the run of the join file named by "
                        "$TESTBED_JOIN (docs/protocol.md#joining-a-run-from-outside)")
    add_run_option_arguments(p)
    add_zenoh_arguments(p)
    g = p.add_argument_group("node")
    g.add_argument("--ready-timeout", type=float, default=120.0, metavar="S",
                   help="give up if the other nodes are not up after S seconds (default %(default)s)")
    g.add_argument("--realtime", action="store_true", help="run the loop under SCHED_FIFO (needs CAP_SYS_NICE)")
    g.add_argument("--cpus", metavar="LIST", help="pin this node to these CPUs, e.g. 2 or 2,3 or 2-3")
    g.add_argument("--rx", choices=RX_MODES, default="thread",
                   help="how control messages are received: thread (zenoh-python's callback thread), direct "
                        "(on Zenoh's own receive thread where the handler never waits), spin (direct, and the "
                        "node's input on the loop's path is polled just before it is due) (default %(default)s)")
    g.add_argument("--rx-spin-us", type=float, metavar="US",
                   help="--rx spin: spin at most this long per sample (default min(1000, T/20 in us))")
    g.add_argument("--parent-pid", type=int, help=argparse.SUPPRESS)
    g.add_argument("--launched", action="store_true", help=argparse.SUPPRESS)  # by testbed run
    g.add_argument("--crash-at", type=int, metavar="K", help="fault injection: raise at sample K")
    g.add_argument("-v", "--verbose", action="store_true", help="log at INFO (start-up, every event)")
    g = p.add_argument_group("rerun (testbed run --rerun passes these)")
    g.add_argument("--rerun-url", metavar="URL", help="stream this node's telemetry to a Rerun gRPC URL")
    g.add_argument("--rerun-save", metavar="PATH.rrd", help="write this node's telemetry to a Rerun file")
    g.add_argument("--recording-id", help="Rerun recording id shared by the nodes of a run (default: --run-id)")
    g = p.add_argument_group("plant")
    g.add_argument("--wait-collector", action="store_true",
                   help="also wait for the launcher's collector before starting")
    g.add_argument("--start-lead", type=float, default=0.2, metavar="S",
                   help="t0 = now + S once everybody is ready (default %(default)s)")
    g.add_argument("--spin-us", type=float, metavar="US",
                   help="busy-wait this long before each sample instant (default min(200, T/20 in us))")
    g.add_argument("--encoder-crash-at", type=int, metavar="K",
                   help="--colocate encoder: fault injection: the colocated encoder raises at sample K (it alone stops)")
    g = p.add_argument_group("encoder")
    g.add_argument("--ack-grace", type=float, metavar="FRACTION",
                   help="wait this fraction of T for a late ack before withholding (default 0.2 d)")
    g = p.add_argument_group("attacker")
    g.add_argument("--corrupt", metavar="K[:range|:length],...",
                   help="fault injection: corrupt the payload of these samples")


def main_node(args) -> int:
    from ..nodes.main import run_node

    return run_node(node_config(args))
