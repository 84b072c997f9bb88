"""The typed configuration of a live run, built once from the command line of ``testbed run``, ``testbed node``,
``testbed record`` and ``testbed conformance`` (``testbed.nodes.options``); nothing below the commands reads an
argparse namespace."""

from __future__ import annotations

from .. import validate
from ..errors import BadInput
from ..nodes.options import NodeConfig, RecorderConfig, RunConfig, RunOptions
from ..wire import transport
from ..wire.session import SessionOptions


def run_options(args) -> RunOptions:
    """The run options (``add_run_option_arguments``) of a parsed command line."""
    return RunOptions(**{k: getattr(args, k, None) for k, _ in RunOptions._OVERRIDES},
                      ack_via_attacker=bool(getattr(args, "ack_via_attacker", False)),
                      separate_ack=bool(getattr(args, "separate_ack", False)),
                      colocate=transport.colocated_roles(getattr(args, "colocate", None)))


def session_options(args) -> SessionOptions:
    """A node's or the recorder's session (``add_zenoh_arguments``)."""
    return SessionOptions(run_id=args.run_id, listen=tuple(args.listen), connect=tuple(args.connect),
                          zenoh_config=args.zenoh_config, topology=args.topology, secret_file=args.secret_file,
                          tls_dir=args.tls_dir, insecure=args.insecure, low_latency=args.low_latency)


def node_config(args) -> NodeConfig:
    """``testbed node``'s configuration."""
    return NodeConfig(role=args.role, scenario=args.scenario, opts=run_options(args), session=session_options(args),
                      **{k: getattr(args, k) for k in (*NodeConfig._VALUED, *NodeConfig._SWITCHES)})


def recorder_config(args) -> RecorderConfig:
    """``testbed record``'s configuration."""
    return RecorderConfig(scenario=args.scenario, opts=run_options(args), session=session_options(args),
                          **{k: getattr(args, k) for k in (*RecorderConfig._VALUED, *RecorderConfig._SWITCHES)})


def pairs(items, sep: str, what: str, roles=transport.ROLES) -> dict[str, str]:
    """Repeated ``ROLE<sep>VALUE`` flags -> {role: value}; one clear line for a malformed one."""
    out = {}
    for it in items:
        role, s, val = it.partition(sep)
        if not s or role not in roles:
            raise BadInput(f"{what} must be ROLE{sep}VALUE with ROLE in {', '.join(roles)}, got {it!r}")
        out[role] = val
    return out


def _number(kind, value: str, flag: str):
    """A time (``float``, seconds) or a sample index (``int``) of ``ROLE@VALUE``: finite and >= 0."""
    try:
        return validate.text_number(value, kind)
    except validate.Invalid as e:
        raise BadInput(f"{flag}: {e}") from None


def run_config(args) -> RunConfig:
    """``testbed run``'s configuration, its ``ROLE=VALUE`` and ``ROLE@VALUE`` flags checked (one line, exit 2)."""
    kills = pairs(args.kill, "@", "--kill", (*transport.ROLES, transport.RECORDER))
    crashes = pairs(args.crash, "@", "--crash")
    return RunConfig(
        scenario=args.scenario, opts=run_options(args), json=args.json,
        run_id=args.run_id, listen=args.listen, node_connect=args.node_connect,
        node_listen=pairs(args.node_listen, "=", "--node-listen"),
        node_prefix=pairs(args.node_prefix, "=", "--node-prefix"),
        zenoh_config=args.zenoh_config, topology=args.topology, secret_file=args.secret_file, tls_dir=args.tls_dir,
        insecure=args.insecure, low_latency=args.low_latency, netns=args.netns, netns_clean=args.netns_clean,
        out=args.out, force=args.force, no_record=args.no_record, on_record_error=args.on_record_error,
        record_loop=args.record_loop,
        rerun=None if args.rerun is None else tuple(args.rerun), rrd=args.rrd, roa=not args.no_roa,
        foxglove=args.foxglove, foxglove_linger=args.foxglove_linger, external=args.external,
        startup_timeout=args.startup_timeout, run_dir=args.run_dir, spawn=args.spawn, realtime=args.realtime,
        cpu=pairs(args.cpu, "=", "--cpu", (*transport.ROLES, transport.RECORDER, transport.LAUNCHER)),
        rx=args.rx, rx_spin_us=args.rx_spin_us, spin_us=args.spin_us, ack_grace=args.ack_grace, verbose=args.verbose,
        progress=getattr(args, "progress", False),
        kill={r: _number(float, v, "--kill") for r, v in kills.items()}, stall=tuple(args.stall),
        crash={r: _number(int, v, "--crash") for r, v in crashes.items()}, corrupt=args.corrupt, cut=tuple(args.cut))
