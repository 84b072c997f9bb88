"""``testbed run SCENARIO --external ROLE``: a run that waits for one node from outside.

The launcher starts every node but ROLE, writes the join file (``testbed.wire.join``, 0600, in the
run's folder), prints its path on stderr and waits (``--startup-timeout``) for a node that reads it
from ``TESTBED_JOIN``; the file goes with the run's other credentials at the end of the run.
"""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import BadInput
from ..nodes.options import T_ns, run_digest
from ..wire import join, transport

#: what ``testbed run`` prints on stderr (one line; ``testbed conformance`` reads it)
ANNOUNCE = "testbed run: join file for the external {role}: {path}"


def add_external_arguments(p) -> None:
    g = p.add_argument_group("external node")
    g.add_argument("--external", choices=transport.ROLES, metavar="ROLE",
                   help="do not start ROLE: write a join file for a node from outside, print its path on stderr "
                        "and wait for that node (--startup-timeout); the node gets the path in $TESTBED_JOIN "
                        "(docs/protocol.md#joining-a-run-from-outside)")


def check(launcher) -> str | None:
    """The external role of the run (None: none), refused with one line where the run cannot have it."""
    role = launcher.cfg.external
    if role is None:
        return None
    if launcher.colocated:
        raise BadInput("--external with --colocate: an external node runs alone in its process")
    for flag, given in (("--kill", launcher.kills), ("--crash", launcher.crashes), ("--node-prefix", launcher.node_prefix),
                        ("--cpu", launcher.cpus)):
        if role in given:
            raise BadInput(f"{flag} {role}: the {role} is external (--external {role}): the testbed does not start it")
    return role


def join_data(launcher) -> dict:
    """The join file's fields (``join.FIELDS``) for the launcher's external role."""
    la, role, sc, opts = launcher, launcher.external, launcher.sc, launcher.opts
    if not la.secure:
        cred = {"kind": "none"}
    elif la.tls:
        d = Path(la.tls_dir)
        cred = {"kind": "mutual_tls", "ca": str(d / "ca.pem"), "cert": str(d / f"{role}.pem"),
                "key": str(d / f"{role}.key")}
    else:
        path = la.secret_for(role)
        cred = {"kind": "user_password", "user": role, "password": transport.Credentials.read(path).password(role),
                "secret_file": str(path)}
    peer = la.topology == "peer"
    ack = la.keys.ack_for_encoder(opts.ack_via_attacker, opts.ack_on_actuation)
    ref = Path(la.cfg.scenario)
    base_dir = str(ref.resolve().parent) if (ref.suffix == ".toml" or ref.exists()) else None
    options = opts.join_fields()  # every run option a node takes (testbed.optionspec)
    return {"join_version": join.JOIN_VERSION, "protocol": join.PROTOCOL_VERSION, "role": role,
            "run_id": la.run_id, "key_prefix": la.keys.prefix, "ack_key": ack[len(la.keys.prefix) + 1:],
            "topology": la.topology, "mode": "peer" if peer else "client", "connect": [la.node_connect],
            "listen": [la.node_listen.get(role) or la.own_listener(role)] if peer else [],
            "low_latency": la.cfg.low_latency, "credentials": cred, "T_ns": T_ns(sc), "n_steps": sc.n_steps,
            "timing": sc.run.timing, "ack_via_attacker": opts.ack_via_attacker, "digest": run_digest(sc, opts),
            "t0_ns": None, "start_lead_ns": 200_000_000, "wait_ready": [*transport.ROLES, transport.COLLECTOR],
            "ready_timeout_s": float(la.cfg.startup_timeout), "run_options": options,
            "scenario": {"name": sc.name, "toml": sc.source, "base_dir": base_dir}}


def write_join(launcher) -> Path | None:
    """Write the join file of the external role (after the run's credentials are made) and say where, on stderr."""
    if launcher.external is None:
        return None
    path = join.write(launcher.run_dir / f"join-{launcher.external}.json", join_data(launcher))
    print(ANNOUNCE.format(role=launcher.external, path=path), file=sys.stderr, flush=True)
    return path


def remove_join(path: Path | None) -> None:
    """At the end of the run (with its other credentials): the join file goes."""
    join.remove(path)


def annotate(summary: dict, role: str | None) -> None:
    """The summary says which role came from outside (``external``); that node has no exit or log of ours."""
    summary["external"] = role
    if role is not None:
        summary["nodes"][role] = {"external": True, "exit_code": None, "log": None}
        for f in summary.get("faults", []):
            if f.get("kind") == "startup_timeout" and role not in (f.get("alive") or ()):
                f["why"] += f"; the external {role} never joined (its join file: TESTBED_JOIN)"
