"""The typed configuration of a live run, built once from the command line of ``testbed run``, ``testbed node``,
``testbed record`` and ``testbed conformance`` (``testbed.nodes.options``, each option defined once:
``testbed.common.optionspec``); nothing below the commands reads an argparse namespace."""

from __future__ import annotations

import argparse

from ..common import optionspec
from ..nodes.options import NodeConfig, RecorderConfig, RunConfig, RunOptions
from ..wire.session import SessionOptions


def run_options(args: argparse.Namespace, command: str = "run") -> RunOptions:
    """The run options (``add_run_option_arguments``) of a parsed command line."""
    return optionspec.from_args(RunOptions, args, command)


def session_options(args: argparse.Namespace, command: str = "node") -> SessionOptions:
    """A process's session (``add_network_arguments``): a node's or the recorder's, or the launcher's (``run``)."""
    return optionspec.from_args(SessionOptions, args, command)


def node_config(args: argparse.Namespace) -> NodeConfig:
    """``testbed node``'s configuration."""
    return optionspec.from_args(NodeConfig, args, "node", role=args.role, scenario=args.scenario,
                                opts=run_options(args, "node"), session=session_options(args, "node"))


def recorder_config(args: argparse.Namespace) -> RecorderConfig:
    """``testbed record``'s configuration."""
    return optionspec.from_args(RecorderConfig, args, "record", scenario=args.scenario,
                                opts=run_options(args, "record"), session=session_options(args, "record"))


def run_config(args: argparse.Namespace) -> RunConfig:
    """``testbed run``'s configuration, its ``ROLE=VALUE`` and ``ROLE@VALUE`` flags checked (one line, exit 2); the
    flags other modules define (recording, viewers, namespaces, a node from outside) by name."""
    return optionspec.from_args(
        RunConfig, args, "run", scenario=args.scenario, opts=run_options(args), session=session_options(args, "run"),
        json=args.json, netns=args.netns, netns_clean=args.netns_clean, out=args.out,
        on_record_error=args.on_record_error, rerun=None if args.rerun is None else tuple(args.rerun), rrd=args.rrd,
        roa=not args.no_roa, external=args.external, cut=tuple(args.cut))
