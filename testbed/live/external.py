"""``testbed run SCENARIO --external ROLE``: a run that waits for one node from outside.

The launcher starts every node but ROLE, writes the join file (``testbed.wire.join``, 0600, in the
run's folder), prints its path on stderr and waits (``--startup-timeout``) for a node that reads it
from ``TESTBED_JOIN``; the file goes with the run's other credentials at the end of the run.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from ..common.errors import BadInput
from ..nodes.options import T_ns, run_digest
from ..record import faults as faultrec
from ..wire import join, transport
from .credentials import RunCredentials

if TYPE_CHECKING:
    from ..nodes.options import RunConfig, RunOptions
    from ..record.faults import Fault
    from ..scenario import Scenario

#: what ``testbed run`` prints on stderr (one line; ``testbed conformance`` reads it)
ANNOUNCE = "testbed run: join file for the external {role}: {path}"


def add_external_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("external node")
    g.add_argument("--external", choices=transport.ROLES, metavar="ROLE",
                   help="do not start ROLE: write a join file for a node from outside, print its path on stderr "
                        "and wait for that node (--startup-timeout); the node gets the path in $TESTBED_JOIN "
                        "(docs/protocol.md#joining-a-run-from-outside)")


def check(cfg: RunConfig, colocated: tuple[str, ...]) -> str | None:
    """The external role of the run (None: none), refused with one line where the run cannot have it
    (``cfg``: the run's ``RunConfig``)."""
    role = cfg.external
    if role is None:
        return None
    if colocated:
        raise BadInput("--external with --colocate: an external node runs alone in its process")
    for flag, given in (("--kill", cfg.kill), ("--crash", cfg.crash), ("--node-prefix", cfg.node_prefix),
                        ("--cpu", cfg.cpu)):
        if role in given:
            raise BadInput(f"{flag} {role}: the {role} is external (--external {role}): the testbed does not start it")
    return role


def join_data(role: str, la: RunCredentials, sc: Scenario, opts: RunOptions, cfg: RunConfig) -> dict:
    """The join file's fields (``join.FIELDS``) for the external ``role`` of the run whose sessions are ``la``
    (``opts``: its ``RunOptions``; ``cfg``: its ``RunConfig``)."""
    if not la.secure:
        cred = {"kind": "none"}
    elif la.tls:
        assert la.tls_dir is not None  # made or given (make_secrets) before a join file is written
        d = Path(la.tls_dir)
        cred = {"kind": "mutual_tls", "ca": str(d / "ca.pem"), "cert": str(d / f"{role}.pem"),
                "key": str(d / f"{role}.key")}
    else:
        path = la.secret_for(role)
        cred = {"kind": "user_password", "user": role, "password": transport.Credentials.read(path).password(role),
                "secret_file": str(path)}
    peer = la.topology == "peer"
    ack = la.keys.ack_for_encoder(opts.ack_via_attacker, opts.ack_on_actuation)
    ref = Path(cfg.scenario)
    base_dir = str(ref.resolve().parent) if (ref.suffix == ".toml" or ref.exists()) else None
    options = opts.join_fields()  # every run option a node takes (testbed.common.optionspec)
    return {"join_version": join.JOIN_VERSION, "protocol": join.PROTOCOL_VERSION, "role": role,
            "run_id": la.run_id, "key_prefix": la.keys.prefix, "ack_key": ack[len(la.keys.prefix) + 1:],
            "topology": la.topology, "mode": "peer" if peer else "client", "connect": [la.node_connect],
            "listen": [la.node_listen.get(role) or la.own_listener(role)] if peer else [],
            "low_latency": cfg.low_latency, "credentials": cred, "T_ns": T_ns(sc), "n_steps": sc.n_steps,
            "timing": sc.run.timing, "ack_via_attacker": opts.ack_via_attacker, "digest": run_digest(sc, opts),
            "t0_ns": None, "start_lead_ns": 200_000_000, "wait_ready": [*transport.ROLES, transport.COLLECTOR],
            "ready_timeout_s": float(cfg.startup_timeout), "run_options": options,
            "scenario": {"name": sc.name, "toml": sc.source, "base_dir": base_dir}}


def write_join(role: str | None, run_dir: Path, la: RunCredentials, sc: Scenario, opts: RunOptions,
               cfg: RunConfig) -> Path | None:
    """Write the join file of the external role (after the run's credentials are made) and say where, on stderr."""
    if role is None:
        return None
    path = join.write(run_dir / f"join-{role}.json", join_data(role, la, sc, opts, cfg))
    print(ANNOUNCE.format(role=role, path=path), file=sys.stderr, flush=True)
    return path


def remove_join(path: Path | None) -> None:
    """At the end of the run (with its other credentials): the join file goes."""
    join.remove(path)


def annotate(summary: dict, role: str | None, faults: Iterable[Fault]) -> None:
    """The summary says which role came from outside (``external``); that node has no exit or log of ours;
    a start-up timeout of the run's ``faults`` says when it never joined."""
    summary["external"] = role
    if role is not None:
        summary["nodes"][role] = {"external": True, "exit_code": None, "log": None}
        for f in faults:
            if f.kind == "startup_timeout" and role not in (faultrec.given(f.alive) or ()):
                f.detail += f"; the external {role} never joined (its join file: TESTBED_JOIN)"
