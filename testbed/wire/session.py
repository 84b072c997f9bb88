"""A process's Zenoh session: its flags, its security (credentials, TLS, access rules) and its config."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..common import optionspec
from ..common.optionspec import option
from . import transport

# ============================================================================ zenoh options
#: ``testbed run --topology auto``: the launcher picks ``peer`` or ``router`` (``testbed.live.credentials``)
AUTO = "auto"


#: the commands that start a run (the launcher's form of the network flags: one endpoint, ``--topology auto``)
LAUNCHERS = ("run", "conformance")
#: the commands of every process of a run
PROCESSES = ("run", "node", "record", "conformance")


def _session(default: Any = None, help: str = "", *, launcher: Any = None, commands: tuple[str, ...] = PROCESSES,
             **kw: Any) -> Any:
    """A session option; ``launcher``: how ``testbed run`` (and ``testbed conformance``, which starts one) takes it."""
    return option(default, help, commands=commands, per={c: launcher for c in LAUNCHERS} if launcher else {}, **kw)


@dataclass(frozen=True)
class SessionOptions:
    """One process's session: run id, endpoints, topology and credentials (the flags of ``add_network_arguments``;
    each field the one definition of its flag, ``testbed.common.optionspec``).

    ``testbed node`` and ``testbed record`` build it from their flags; the launcher builds one for each process it
    starts (``testbed.live.credentials``) and for its own session, and passes it on as flags (``argv``).  In the
    launcher's configuration (``RunConfig.session``) ``run_id`` None makes one, ``listen`` holds at most one
    endpoint, and ``topology`` may be ``auto``."""

    run_id: str | None = _session(transport.DEFAULT_RUN_ID, "key prefix testbed/RUN_ID/... (default %(default)s)",
                                  launcher={"default": None,
                                            "help": "key prefix testbed/RUN_ID/... (default: unique per run)"})
    listen: tuple[str, ...] = _session(
        (), "endpoint to listen on, e.g. tcp/10.0.0.2:7447 (repeatable)", metavar="ENDPOINT", repeat=True,
        launcher={"repeat": False, "help": "the launcher's endpoint (default tcp/127.0.0.1:<free port>); nodes "
                                           "connect to it"})
    connect: tuple[str, ...] = _session((), "endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable)",
                                        metavar="ENDPOINT", repeat=True, commands=("node", "record"))
    zenoh_config: str | None = _session(
        help="Zenoh JSON5 config read first (e.g. TLS certificates); flags override it", metavar="FILE",
        launcher={"help": "Zenoh JSON5 config for every session (e.g. TLS certificates); flags override it"})
    topology: str = _session(
        "router", "router: one process (under testbed run, the launcher) routes and checks every message (default); "
                  "peer: direct links between the processes, each mutual TLS (--tls-dir), and every process checks "
                  "what it receives", choices=transport.TOPOLOGIES, group="security",
        launcher={"default": AUTO, "choices": (AUTO, *transport.TOPOLOGIES),
                  "help": "auto (default): peer when every node runs on this host, router otherwise (a --node-prefix, "
                          "a --zenoh-config, a non-loopback or plain TCP endpoint, or a --secret-file; docs/live.md); "
                          "router: the launcher routes and checks every message; peer: direct links between the "
                          "processes, each mutual TLS (certificates made for the run, or --tls-dir), and every process "
                          "checks what it receives"})
    secret_file: str | None = _session(
        help="the run's credentials (a 0600 file of user:password lines; make one with 'testbed secret PATH'); testbed "
             "run makes new ones for each run unless given one, which nodes on other hosts need at the same path",
        metavar="PATH", group="security")
    tls_dir: str | None = _session(
        help="--topology peer: the run's TLS folder (ca.pem, NAME.pem, NAME.key; make one with 'testbed secret --tls "
             "DIR'); testbed run makes certificates for each run unless given one. --topology router with --tls-dir "
             "and no --secret-file: the router topology over mutual TLS, the router checking by certificate name "
             "(docs/protocol.md)", metavar="DIR", group="security")
    insecure: bool = _session(False, "no authentication and no access control: any local process can join, stop or "
                                     "steer the run (recorded as such)", group="security")
    low_latency: bool = _session(False, "Zenoh's low-latency transport (no batching, no priority queues); every process "
                                        "of a run must use it or none (testbed run: all of them)", group="security")

    @classmethod
    def of(cls, command: str) -> SessionOptions:
        """The session ``command``'s flags make when none is given (``testbed run``'s: ``topology`` auto)."""
        return cls(**optionspec.defaults(cls, command))

    @property
    def router_tls(self) -> bool:
        """The router topology with ``--tls-dir`` and no ``--secret-file``: the links are mutual TLS and the router
        checks every message by certificate name (a client that cannot authenticate with a password, such as a
        zenoh-pico device, joins this way; docs/protocol.md)."""
        return self.topology == "router" and bool(self.tls_dir) and not self.secret_file and not self.insecure

    def argv(self, command: str = "node") -> list[str]:
        """The same session as flags of ``command`` (``testbed node`` / ``testbed record``, or ``testbed run`` for the
        launcher's form; credentials by path, never the secret)."""
        return optionspec.argv(self, command)


def add_security_arguments(g: argparse._ActionsContainer, launcher: bool = False) -> None:
    """``--topology``, ``--secret-file``, ``--tls-dir``, ``--insecure``, ``--low-latency``: every process of a run
    (``testbed run``, ``testbed node``, ``testbed record``) takes the same flags.  The launcher (``testbed run``)
    also takes ``--topology auto``, its default: it decides for the run and passes the topology on."""
    optionspec.add_arguments(g, SessionOptions, "run" if launcher else "node", group=g, section="security")


def add_network_arguments(g: argparse._ActionsContainer, launcher: bool = False, command: str | None = None) -> None:
    """The network flags of every process of a run (``SessionOptions``): ``--run-id``, ``--listen``, ``--zenoh-config``
    and the security flags; a node and the recorder (``launcher=False``) also take ``--connect``.  The launcher
    (``testbed run``, and ``testbed conformance``: ``command``) listens on one endpoint and makes a run id unless
    given one."""
    optionspec.add_arguments(g, SessionOptions, command or ("run" if launcher else "node"), group=g)


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    """The ``zenoh`` group of ``testbed node`` and ``testbed record``."""
    add_network_arguments(p.add_argument_group("zenoh"))


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


def zenoh_config(s: SessionOptions, role: str, keys: transport.Keys, *, hub: bool = False,
                 colocate: tuple[str, ...] = ()) -> Any:
    """The session of ``role``: a node, the recorder, or (``hub``) the run's router or first peer.

    Standalone defaults (no endpoint given): the plant is the hub and listens on tcp/127.0.0.1:7447, the
    others connect to it.  Router topology: the hub (the launcher, or a standalone plant) is the run's
    router and checks every message; the others are its clients.  Unless ``insecure``, the session
    authenticates with the secret file's line of ``role``; the hub accepts the file's other lines.  Peer
    topology: every process is a peer, every link mutual TLS with ``role``'s certificate of the
    ``tls_dir`` folder, and every process checks what it receives.  The one builder of every process's
    session, the launcher's own included (``testbed.live.credentials``).
    """
    from ..common.errors import BadInput

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
    common: dict[str, Any] = dict(listen=listen, connect=connect, config_file=s.zenoh_config, colocate=tuple(colocate),
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


def session_config(role: str, mode: str, keys: transport.Keys, *, listen: list[str] | tuple[str, ...] = (),
                   connect: list[str] | tuple[str, ...] = (), config_file: str | Path | None = None,
                   colocate: tuple[str, ...] = (), low_latency: bool = False, insecure: bool = False,
                   tls_dir: str | Path | None = None, secret_file: str | Path | None = None,
                   accepts: bool = False) -> Any:
    """The Zenoh config of one process of a run, the one place a session's security is put together.

    ``mode`` "peer": mutual TLS with ``role``'s certificate of ``tls_dir``, and the access rules checked
    by every receiver (by certificate common name).  "router"/"client" with ``tls_dir`` and no
    ``secret_file``: mutual TLS too, and the router (``accepts``) checks the access rules by certificate
    common name.  Otherwise user/password: ``role``'s line of the
    ``secret_file``; a process that ``accepts`` others (the run's router: the launcher, or a standalone
    plant) also authenticates them against the file's lines and checks the access rules.  ``insecure``:
    neither.  Used by the nodes and the recorder (``zenoh_config``) and the launcher's own session.
    """
    from ..common.errors import BadInput

    common: dict[str, Any] = {"listen": list(listen), "connect": list(connect), "config_file": config_file,
                              "mode": mode, "low_latency": low_latency}
    if insecure:
        return transport.make_config(**common)
    if mode == "peer":
        assert tls_dir is not None  # zenoh_config refuses a peer without one (PEER_NEEDS_TLS)
        return transport.make_config(**common, acl=transport.acl_config(keys, colocate, by="cert_common_names"),
                                     tls=transport.TlsCredentials(tls_dir).zenoh(role))
    if tls_dir is not None and secret_file is None:  # router topology over mutual TLS: the router checks by name
        acl = transport.acl_config(keys, colocate, by="cert_common_names") if accepts else None
        return transport.make_config(**common, acl=acl, tls=transport.TlsCredentials(tls_dir).zenoh(role))
    assert secret_file is not None  # zenoh_config refuses a session without one ("no --secret-file")
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
