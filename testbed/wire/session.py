"""A process's Zenoh session: its flags, its security (credentials, TLS, access rules) and its config."""

from __future__ import annotations

import argparse

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


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--run-id", default=transport.DEFAULT_RUN_ID,
                   help="key prefix testbed/RUN_ID/... (default %(default)s)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/10.0.0.2:7447 (repeatable)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 config read first (e.g. TLS certificates); flags override it")
    add_security_arguments(g)


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


def router_tls(args) -> bool:
    """``testbed node``/``testbed record`` in the router topology with ``--tls-dir`` and no ``--secret-file``:
    the links are mutual TLS and the router checks every message by certificate name (a client that cannot
    authenticate with a password, such as a zenoh-pico device, joins this way; docs/protocol.md)."""
    return (getattr(args, "topology", "router") == "router" and bool(getattr(args, "tls_dir", None))
            and not getattr(args, "secret_file", None) and not getattr(args, "insecure", False))


def security_info(args) -> dict:
    """How a process's session is secured (it goes into the recording and the summary)."""
    return {"authenticated": not args.insecure, "topology": args.topology,
            "access_control": "none" if args.insecure else access_control(args.topology),
            "transport": transport_security(args.topology, args.insecure, router_tls(args)),
            "low_latency": bool(getattr(args, "low_latency", False))}


def zenoh_config(args, role: str, keys: transport.Keys):
    """The session of ``role`` (a node or the recorder).

    Standalone defaults: the plant listens on tcp/127.0.0.1:7447, the others connect to
    it.  Router topology: the hub (the launcher, or a standalone plant) is the run's
    router and checks every message; the others are its clients.  Unless ``--insecure``,
    the session authenticates with the secret file's line of ``role``; the router accepts
    the file's other lines.  Peer topology: every process is a peer, every link mutual TLS
    with ``role``'s certificate of the ``--tls-dir`` folder, and every process checks what
    it receives.
    """
    from ..errors import BadInput

    hub = role == "plant" and not getattr(args, "launched", False)
    peer = args.topology == "peer"
    tls_router = router_tls(args)
    hub_ep = transport.DEFAULT_HUB.replace("tcp/", "tls/", 1) if (peer or tls_router) and not args.insecure \
        else transport.DEFAULT_HUB
    listen, connect = list(args.listen), list(args.connect)
    if not listen and not connect and not args.zenoh_config:
        if hub:
            listen = [hub_ep]
        else:
            connect = [hub_ep]
    mode = "peer" if peer else ("router" if hub else "client")
    if tls_router:
        transport.require_tls((*listen, *connect), "--topology router --tls-dir")
        return session_config(role, mode, keys, listen=listen, connect=connect, config_file=args.zenoh_config,
                              colocate=transport.colocated_roles(getattr(args, "colocate", None)),
                              low_latency=bool(getattr(args, "low_latency", False)), tls_dir=args.tls_dir,
                              accepts=hub)
    if not args.insecure and not peer and not args.secret_file:
        raise BadInput("no --secret-file: make one with 'testbed secret PATH' and give it to every process "
                       "of the run (or run unauthenticated with --insecure)")
    if not args.insecure and peer:
        if not getattr(args, "tls_dir", None):
            raise BadInput(PEER_NEEDS_TLS)
        transport.require_tls((*listen, *connect))
    return session_config(role, mode, keys, listen=listen, connect=connect, config_file=args.zenoh_config,
                          colocate=transport.colocated_roles(getattr(args, "colocate", None)),
                          low_latency=bool(getattr(args, "low_latency", False)), insecure=args.insecure,
                          tls_dir=getattr(args, "tls_dir", None), secret_file=args.secret_file, accepts=hub)


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
