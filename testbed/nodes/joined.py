"""``testbed node ROLE`` with ``TESTBED_JOIN`` and no scenario: the node's flags and scenario from the join file."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from ..wire import join
from .options import NodeConfig, RunOptions

if TYPE_CHECKING:
    from ..scenario import Scenario


def apply(cfg: NodeConfig) -> tuple:
    """Read ``$TESTBED_JOIN``: the checked ``JoinFile`` and ``cfg`` set as the launcher sets its own nodes'.

    A file of another role, or unusable credentials, is ``BadInput`` (one line, exit 2)."""
    from ..common.errors import BadInput

    jf = join.read()
    role = cfg.role
    if jf.role != role:
        raise BadInput(f"join file {jf.path}: it is for the {jf.role}, not the {role}")
    cred = jf.credentials
    tls_dir = secret_file = None
    if cred["kind"] == "mutual_tls":
        folder = Path(cred["cert"]).parent
        want = {"ca": folder / "ca.pem", "cert": folder / f"{role}.pem", "key": folder / f"{role}.key"}
        if any(Path(cred[k]) != v for k, v in want.items()):
            raise BadInput(f"join file {jf.path}: the bundled node reads ca.pem, {role}.pem and {role}.key "
                           "of one folder")
        tls_dir = str(folder)
    elif cred["kind"] == "user_password":
        secret_file = cred["secret_file"]
    session = dataclasses.replace(cfg.session, run_id=jf.run_id, connect=tuple(jf.connect), listen=tuple(jf.listen),
                                  topology=jf.topology, low_latency=jf.low_latency, insecure=cred["kind"] == "none",
                                  tls_dir=tls_dir, secret_file=secret_file)
    opts = RunOptions.of_join(jf.run_options, f"join file {jf.path}")
    if opts.colocate:
        raise BadInput(f"join file {jf.path}: an external node with --colocate is not supported")
    options = {f.name: getattr(opts, f.name) for f in dataclasses.fields(RunOptions) if f.name in jf.run_options}
    # a node of a testbed run: it waits for the collector and stops when it goes
    return jf, dataclasses.replace(cfg, opts=dataclasses.replace(cfg.opts, **options), session=session,
                                   ready_timeout=float(jf.ready_timeout_s), start_lead=jf.start_lead_ns / 1e9,
                                   launched=True)


def scenario(jf: join.JoinFile, overrides: dict | None = None) -> Scenario:
    """The scenario the join file embeds (its text, as the run read it: the same digest), with the run's
    ``overrides`` applied in the one parse."""
    from .. import scenario as scn
    from ..record.tracereader import read_recording_trace

    s = jf.scenario
    return scn.loads(s["toml"], name=s["name"], where=f"{jf.path} (scenario {s['name']})", base_dir=s["base_dir"],
                     check_design=False, read_recording_trace=read_recording_trace, overrides=overrides)
