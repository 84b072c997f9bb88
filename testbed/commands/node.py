"""``testbed node ROLE [SCENARIO]``: one node of a live run (``testbed.nodes.main``), its flags.

``testbed run`` starts its nodes with these flags (``NodeConfig.argv``), forked or exec'd; a node started
by hand or from outside (``TESTBED_JOIN``) takes the same."""

from __future__ import annotations

import argparse

from ..common import optionspec
from ..nodes.options import NodeConfig, add_run_option_arguments
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
    optionspec.add_arguments(p, NodeConfig, "node")


def main_node(args: argparse.Namespace) -> int:
    from ..nodes.main import run_node

    return run_node(node_config(args))
