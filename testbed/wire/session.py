"""A process's Zenoh session: its flags, its security (credentials, TLS, access rules) and its config."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from . import transport

# ============================================================================ zenoh options
#: ``testbed run --topology auto``: the launcher picks ``peer`` or ``router`` (``testbed.live.credentials``)
AUTO = "auto"


def add_security_arguments(g, launcher: bool = False) -> None:
    """``--topology``, ``--secret-file``, ``--tls-dir``, ``--insecure``, ``--low-latency``: every process of a run
    (``testbed run``, ``testbed node``, ``testbed record``) takes the same flags.  The launcher (``testbed run``)
    also takes ``--topology auto``, its default: it decides for the run and passes the topology on."""
    if launcher:
        g.add_argument("--topology", choices=(AUTO, *transport.TOPOLOGIES), default=AUTO,
                       help="auto (default): peer when every node runs on this host, router otherwise (a "
                            "--node-prefix, a --zenoh-config, a non-loopback or plain TCP endpoint, or a "
                            "--secret-file; docs/live.md); router: the launcher routes and checks every message; "
                            "peer: direct links between the processes, each mutual TLS (certificates made for the "
                            "run, or --tls-dir), and every process checks what it receives")
    else:
        g.add_argument("--topology", choices=transport.TOPOLOGIES, default="router",
                       help="router: one process (under testbed run, the launcher) routes and checks every message "
                            "(default); peer: direct links between the processes, each mutual TLS (--tls-dir), and "
                            "every process checks what it receives")
    g.add_argument("--secret-file", metavar="PATH",
                   help="the run's credentials (a 0600 file of user:password lines; make one with 'testbed "
                        "secret PATH'); testbed run makes new ones for each run unless given one, which nodes on "
                        "other hosts need at the same path")
    g.add_argument("--tls-dir", metavar="DIR",
                   help="--topology peer: the run's TLS folder (ca.pem, NAME.pem, NAME.key; make one with "
                        "'testbed secret --tls DIR'); testbed run makes certificates for each run unless given one. "
                        "--topology router with --tls-dir and no --secret-file: the router topology over mutual TLS, "
                        "the router checking by certificate name (docs/protocol.md)")
    g.add_argument("--insecure", action="store_true",
                   help="no authentication and no access control: any local process can join, stop or steer "
                        "the run (recorded as such)")
    g.add_argument("--low-latency", action="store_true",
                   help="Zenoh's low-latency transport (no batching, no priority queues); every process of a run "
                        "must use it or none (testbed run: all of them)")


def add_network_arguments(g, launcher: bool = False) -> None:
    """The network flags of every process of a run: ``--run-id``, ``--listen``, ``--zenoh-config`` and the security
    flags (``add_security_arguments``); a node and the recorder (``launcher=False``) also take ``--connect``.  The
    launcher (``testbed run``) listens on one endpoint and makes a run id unless given one."""
    if launcher:
        g.add_argument("--run-id", help="key prefix testbed/RUN_ID/... (default: unique per run)")
        g.add_argument("--listen", metavar="ENDPOINT",
                       help="the launcher's endpoint (default tcp/127.0.0.1:<free port>); nodes connect to it")
    else:
        g.add_argument("--run-id", default=transport.DEFAULT_RUN_ID,
                       help="key prefix testbed/RUN_ID/... (default %(default)s)")
        g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/10.0.0.2:7447 (repeatable)")
        g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 config for every session (e.g. TLS certificates); flags override it" if launcher
                   else "Zenoh JSON5 config read first (e.g. TLS certificates); flags override it")
    add_security_arguments(g, launcher=launcher)


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    """The ``zenoh`` group of ``testbed node`` and ``testbed record``."""
    add_network_arguments(p.add_argument_group("zenoh"))


@dataclass(frozen=True)
class SessionOptions:
    """One process's session: run id, endpoints, topology and credentials (the flags of ``add_network_arguments``).

    ``testbed node`` and ``testbed record`` build it from their flags; the launcher builds one for each process it
    starts (``testbed.live.credentials``) and for its own session, and passes it on as flags (``argv``)."""

    run_id: str = transport.DEFAULT_RUN_ID
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    zenoh_config: str | None = None
    topology: str = "router"
    secret_file: str | None = None
    tls_dir: str | None = None
    insecure: bool = False
    low_latency: bool = False

    @property
    def router_tls(self) -> bool:
        """The router topology with ``--tls-dir`` and no ``--secret-file``: the links are mutual TLS and the router
        checks every message by certificate name (a client that cannot authenticate with a password, such as a
        zenoh-pico device, joins this way; docs/protocol.md)."""
        return self.topology == "router" and bool(self.tls_dir) and not self.secret_file and not self.insecure

    def argv(self) -> list[str]:
        """The same session as flags of ``testbed node`` / ``testbed record`` (credentials by path, never the secret)."""
        out = ["--run-id", self.run_id, "--topology", self.topology]
        for ep in self.connect:
            out += ["--connect", ep]
        for ep in self.listen:
            out += ["--listen", ep]
        if self.tls_dir:
            out += ["--tls-dir", str(self.tls_dir)]
        if self.secret_file:
            out += ["--secret-file", str(self.secret_file)]
        if self.insecure:
            out.append("--insecure")
        if self.low_latency:
            out.append("--low-latency")
        if self.zenoh_config:
            out += ["--zenoh-config", str(self.zenoh_config)]
        return out


PEER_NEEDS_TLS = ("--topology peer: no --tls-dir: its links are mutual TLS; make the folder with "
                  "'testbed secret --tls DIR' and give it to every process of the run (or run unauthenticated "
                  "with --insecure)")


def access_control(topology: str) -> str:
    """Who checks the messages of a run (the ``access_control`` of its ``security``)."""
    return "every message, by every receiver" if topology == "peer" else "every message"


def transport_security(topology: str, insecure: bool, tls: bool = False) -> str:
    """How the links of a run are authenticated (the ``transport`` of its ``security``); ``tls``: a router
    topology of nodes started by hand with ``--tls-dir`` and no ``--secret-file`` (``router_tls``)."""
    return "tcp" if insecure else ("mutual tls" if topology == "peer" or tls else "user/password")


def security_info(s: SessionOptions) -> dict:
    """How a process's session is secured (it goes into the recording and the summary)."""
    return {"authenticated": not s.insecure, "topology": s.topology,
            "access_control": "none" if s.insecure else access_control(s.topology),
            "transport": transport_security(s.topology, s.insecure, s.router_tls),
            "low_latency": s.low_latency}


def zenoh_config(s: SessionOptions, role: str, keys: transport.Keys, *, hub: bool = False, colocate=()):
    """The session of ``role``: a node, the recorder, or (``hub``) the run's router or first peer.

    Standalone defaults (no endpoint given): the plant is the hub and listens on tcp/127.0.0.1:7447, the
    others connect to it.  Router topology: the hub (the launcher, or a standalone plant) is the run's
    router and checks every message; the others are its clients.  Unless ``insecure``, the session
    authenticates with the secret file's line of ``role``; the hub accepts the file's other lines.  Peer
    topology: every process is a peer, every link mutual TLS with ``role``'s certificate of the
    ``tls_dir`` folder, and every process checks what it receives.  The one builder of every process's
    session, the launcher's own included (``testbed.live.credentials``).
    """
    from ..errors import BadInput

    peer = s.topology == "peer"
    hub_ep = transport.DEFAULT_HUB.replace("tcp/", "tls/", 1) if (peer or s.router_tls) and not s.insecure \
        else transport.DEFAULT_HUB
    listen, connect = list(s.listen), list(s.connect)
    if not listen and not connect and not s.zenoh_config:
        if hub:
            listen = [hub_ep]
        else:
            connect = [hub_ep]
    mode = "peer" if peer else ("router" if hub else "client")
    common = dict(listen=listen, connect=connect, config_file=s.zenoh_config, colocate=tuple(colocate),
                  low_latency=s.low_latency, accepts=hub)
    if s.router_tls:
        transport.require_tls((*listen, *connect), "--topology router --tls-dir")
        return session_config(role, mode, keys, tls_dir=s.tls_dir, **common)
    if not s.insecure and not peer and not s.secret_file:
        raise BadInput("no --secret-file: make one with 'testbed secret PATH' and give it to every process "
                       "of the run (or run unauthenticated with --insecure)")
    if not s.insecure and peer:
        if not s.tls_dir:
            raise BadInput(PEER_NEEDS_TLS)
        transport.require_tls((*listen, *connect))
    return session_config(role, mode, keys, insecure=s.insecure, tls_dir=s.tls_dir, secret_file=s.secret_file,
                          **common)


def session_config(role: str, mode: str, keys: transport.Keys, *, listen=(), connect=(), config_file=None,
                   colocate=(), low_latency: bool = False, insecure: bool = False, tls_dir=None, secret_file=None,
                   accepts: bool = False):
    """The Zenoh config of one process of a run, the one place a session's security is put together.

    ``mode`` "peer": mutual TLS with ``role``'s certificate of ``tls_dir``, and the access rules checked
    by every receiver (by certificate common name).  "router"/"client" with ``tls_dir`` and no
    ``secret_file``: mutual TLS too, and the router (``accepts``) checks the access rules by certificate
    common name.  Otherwise user/password: ``role``'s line of the
    ``secret_file``; a process that ``accepts`` others (the run's router: the launcher, or a standalone
    plant) also authenticates them against the file's lines and checks the access rules.  ``insecure``:
    neither.  Used by the nodes and the recorder (``zenoh_config``) and the launcher's own session.
    """
    from ..errors import BadInput

    common = {"listen": list(listen), "connect": list(connect), "config_file": config_file, "mode": mode,
              "low_latency": low_latency}
    if insecure:
        return transport.make_config(**common)
    if mode == "peer":
        return transport.make_config(**common, acl=transport.acl_config(keys, colocate, by="cert_common_names"),
                                     tls=transport.TlsCredentials(tls_dir).zenoh(role))
    if tls_dir is not None and secret_file is None:  # router topology over mutual TLS: the router checks by name
        acl = transport.acl_config(keys, colocate, by="cert_common_names") if accepts else None
        return transport.make_config(**common, acl=acl, tls=transport.TlsCredentials(tls_dir).zenoh(role))
    cred = transport.Credentials.read(secret_file)
    if accepts:
        missing = [u for u in (*transport.ROLES, transport.RECORDER) if u not in cred.users]
        if missing:
            raise BadInput(f"secret file {secret_file}: no line for {', '.join(missing)} (a {mode} that "
                           "accepts the others needs all of them)")
    # the launcher's own line may be missing from a secret file made for nodes started by hand
    password = cred.users.get(role) if role == transport.LAUNCHER else cred.password(role)
    return transport.make_config(**common, user=role, password=password,
                                 dictionary_file=secret_file if accepts else None,
                                 acl=transport.acl_config(keys, colocate) if accepts else None)
