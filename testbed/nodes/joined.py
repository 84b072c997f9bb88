"""``testbed node ROLE`` with ``TESTBED_JOIN`` and no scenario: the node's flags and scenario from the join file."""

from __future__ import annotations

from pathlib import Path

from ..wire import join


def apply(args):
    """Read ``$TESTBED_JOIN`` and set ``args`` as the launcher sets its own nodes' flags; the checked ``JoinFile``.

    A file of another role, or unusable credentials, is ``BadInput`` (one line, exit 2)."""
    from ..errors import BadInput

    jf = join.read()
    if jf.role != args.role:
        raise BadInput(f"join file {jf.path}: it is for the {jf.role}, not the {args.role}")
    args.run_id = jf.run_id
    args.connect, args.listen = list(jf.connect), list(jf.listen)
    args.topology = jf.topology
    args.low_latency = jf.low_latency
    cred = jf.credentials
    args.insecure = cred["kind"] == "none"
    args.tls_dir = args.secret_file = None
    if cred["kind"] == "mutual_tls":
        folder = Path(cred["cert"]).parent
        want = {"ca": folder / "ca.pem", "cert": folder / f"{args.role}.pem", "key": folder / f"{args.role}.key"}
        if any(Path(cred[k]) != v for k, v in want.items()):
            raise BadInput(f"join file {jf.path}: the bundled node reads ca.pem, {args.role}.pem and {args.role}.key "
                           "of one folder")
        args.tls_dir = str(folder)
    elif cred["kind"] == "user_password":
        args.secret_file = cred["secret_file"]
    for k, v in jf.run_options.items():
        if k == "colocate":
            v = tuple(v or ())
            if v:
                raise BadInput(f"join file {jf.path}: an external node with --colocate is not supported")
        if not hasattr(args, k):
            raise BadInput(f"join file {jf.path}: unknown run option {k!r}")
        setattr(args, k, v)
    args.ready_timeout = float(jf.ready_timeout_s)
    args.start_lead = jf.start_lead_ns / 1e9
    args.launched = True  # a node of a testbed run: it waits for the collector and stops when it goes
    return jf


def scenario(jf):
    """The scenario the join file embeds (its text, as the run read it: the same digest)."""
    from .. import scenario as scn

    s = jf.scenario
    return scn.loads(s["toml"], name=s["name"], where=f"{jf.path} (scenario {s['name']})", base_dir=s["base_dir"],
                     check_design=False)
