"""Zenoh transport: session configuration and every key expression of a live run.

All key expressions live here, under one prefix per run, ``testbed/<run_id>/``:

==============================  =====================  ======================================
key (after the prefix)          publisher -> reader    message (``testbed.wire.messages``)
==============================  =====================  ======================================
``loop/sensor``                 plant -> encoder       ``Sensor``     x_k (control path)
``loop/symbol/tx``              encoder -> attacker    ``Symbol``     packed symbol bits
``loop/symbol/rx``              attacker -> controller ``Symbol``     forwarded symbol
``loop/actuation``              controller -> plant    ``Actuation``  theta_k, u_k; with the ideal
                                (and -> encoder)                      ack also last_rx: the ack
``loop/ack/tx``                 controller -> encoder  ``Ack``        theta_k as a message of its own
                                (or -> attacker)                      (``--separate-ack``), or into
                                                                      the attacker
``loop/ack/rx``                 attacker -> encoder    ``Ack``        ack routed through the attacker
``telemetry/<node>``            each node              ``PlantTelemetry`` ... per sample
``attacker/status``             attacker               ``AttackerStatus`` on every change
``events/<node>``               each node              ``Event``      faults, saturations, ...
``summary/<node>``              each node              ``NodeSummary`` once, at exit
``control/start``               plant (time master)    ``Start``      t0 and run identity
``control/stop``                plant or launcher      ``Stop``
``alive/<node>``                liveliness tokens      present while a node's session is open
``ready/<node>``                liveliness tokens      node warmed up and sees all its peers
==============================  =====================  ======================================

Sessions.  Multicast scouting is off, so nothing else on the network joins a run:
processes meet through explicit endpoints.  Two topologies (``TOPOLOGIES``):

* ``router`` (default): one process (the launcher, or a standalone plant) is the
  run's Zenoh router; every other process is a client of it.  Every link is
  opened by a client and accepted by the router, so the router knows who is at
  the other end of every link and enforces least privilege on every message
  (``acl_config``: each process may publish only on its own keys).
* ``peer``: every process is a peer and gossip links every pair directly (one
  hop less per message).  Every link is mutual TLS (``TlsCredentials``): both
  ends present a certificate of the run's own authority, whose common name is the
  process's name, so each end knows who is at the other, whichever opened the
  link, and every process checks every message it receives (the same
  ``acl_config``, by certificate name).  User/password authentication cannot do
  this in a mesh: only the end that accepted a link learns the other's name (and
  a mesh of such peers opening links to each other at the same moment sometimes
  never completed here, about one start-up in six).  ``--insecure``: plain TCP,
  no authentication.

Authentication: in the router topology (``Credentials``) a run has one password
per process, made for the run and kept in 0600 files; a session that presents no
or a wrong password gets no link at all (it can neither receive nor publish).  In
the peer topology (``TlsCredentials``) a run has one key and certificate per
process, signed by an authority made for the run whose own key is thrown away at
once: no other certificate can be made for it.  ``--insecure`` runs without, on
request.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = "testbed"
ROLES = ("plant", "encoder", "attacker", "controller")
COLLECTOR = "collector"          # the launcher's liveliness name
RECORDER = "recorder"
LAUNCHER = "launcher"            # the launcher's user name (its liveliness name is COLLECTOR)
USERS = (*ROLES, RECORDER, LAUNCHER)
TOPOLOGIES = ("router", "peer")
MAX_MESSAGE_BYTES = 1 << 20      # a received message above this size is dropped (a run's are a few kB)
CLIENT_CONNECT_TIMEOUT_MS = 30_000  # a client waits this long for its router before it gives up
RETRY_INIT_MS = 10  # the first retry of a refused connect (doubling up to 1 s)
DEFAULT_RUN_ID = "default"
DEFAULT_HUB = "tcp/127.0.0.1:7447"   # standalone nodes: the plant listens here, the others connect
LOOPBACK_ANY = "tcp/127.0.0.1:0"     # a peer's own listener for direct links (loopback only)
TLS_LOOPBACK_ANY = "tls/127.0.0.1:0"  # ... with TLS (the authenticated peer topology)


@dataclass(frozen=True)
class Keys:
    """The key expressions of one run (``Keys.for_run(run_id)``)."""

    run_id: str
    prefix: str

    @classmethod
    def for_run(cls, run_id: str = DEFAULT_RUN_ID) -> "Keys":
        if not run_id or any(c in run_id for c in "/*$?#"):
            raise ValueError(f"run id {run_id!r} must be a non-empty key chunk (no / * $ ? #)")
        return cls(run_id=run_id, prefix=f"{ROOT}/{run_id}")

    # ---- control path
    @property
    def sensor(self) -> str:
        return f"{self.prefix}/loop/sensor"

    @property
    def symbol_tx(self) -> str:
        return f"{self.prefix}/loop/symbol/tx"

    @property
    def symbol_rx(self) -> str:
        return f"{self.prefix}/loop/symbol/rx"

    @property
    def actuation(self) -> str:
        return f"{self.prefix}/loop/actuation"

    @property
    def ack_tx(self) -> str:
        return f"{self.prefix}/loop/ack/tx"

    @property
    def ack_rx(self) -> str:
        return f"{self.prefix}/loop/ack/rx"

    def ack_for_encoder(self, via_attacker: bool, on_actuation: bool = False) -> str:
        """Where the encoder reads theta_k: the attacker's forward, the actuation it rides on, or ack/tx."""
        if via_attacker:
            return self.ack_rx
        return self.actuation if on_actuation else self.ack_tx

    # ---- telemetry and bookkeeping
    def telemetry(self, node: str) -> str:
        return f"{self.prefix}/telemetry/{node}"

    def events(self, node: str) -> str:
        return f"{self.prefix}/events/{node}"

    def summary(self, node: str) -> str:
        return f"{self.prefix}/summary/{node}"

    @property
    def summaries_held(self) -> str:
        """The launcher's collector answers a query here with the roles whose ``NodeSummary`` it holds: a node
        closes its session once its own is among them (``NodeContext.summary_received``)."""
        return f"{self.prefix}/collector/summaries"

    @property
    def attacker_status(self) -> str:
        return f"{self.prefix}/attacker/status"

    @property
    def start(self) -> str:
        return f"{self.prefix}/control/start"

    @property
    def stop(self) -> str:
        return f"{self.prefix}/control/stop"

    def alive(self, node: str = "*") -> str:
        return f"{self.prefix}/alive/{node}"

    def ready(self, node: str = "*") -> str:
        return f"{self.prefix}/ready/{node}"

    @property
    def all(self) -> str:
        return f"{self.prefix}/**"

    def table(self) -> list[tuple[str, str]]:
        """(name, key expression) of every key of a run."""
        rows = [("sensor", self.sensor), ("symbol_tx", self.symbol_tx), ("symbol_rx", self.symbol_rx),
                ("actuation", self.actuation), ("ack_tx", self.ack_tx), ("ack_rx", self.ack_rx)]
        rows += [(f"telemetry_{r}", self.telemetry(r)) for r in ROLES]
        rows += [("attacker_status", self.attacker_status), ("events", self.events("<node>")),
                 ("summary", self.summary("<node>")), ("summaries_held", self.summaries_held),
                 ("start", self.start), ("stop", self.stop),
                 ("alive", self.alive("<node>")), ("ready", self.ready("<node>"))]
        return rows

    @staticmethod
    def node_of(key: str) -> str:
        """Last chunk of a key expression (the node name of telemetry/events/alive keys)."""
        return str(key).rsplit("/", 1)[-1]


def make_config(listen: list[str] | tuple[str, ...] = (), connect: list[str] | tuple[str, ...] = (),
                config_file: str | Path | None = None, multicast: bool = False, *, mode: str = "peer",
                user: str | None = None, password: str | None = None, dictionary_file: str | Path | None = None,
                acl: dict | None = None, low_latency: bool = False, tls: dict | None = None) -> Any:
    """A ``zenoh.Config``: explicit endpoints, multicast scouting off.

    ``mode``: "peer", "router" or "client" (a client has no listener of its own).
    ``config_file`` (JSON5, e.g. with a ``transport/link/tls`` section) is read
    first; mode, scouting, ``listen`` and ``connect`` given here override it.
    With no ``listen`` endpoint a peer or router listens on loopback only (Zenoh's
    own default would be every interface).  ``user``/``password``: the credentials
    this session presents; ``dictionary_file``: the ``user:password`` lines it
    accepts from the sessions that connect to it; ``acl``: Zenoh access control
    (``acl_config``).  ``low_latency``: Zenoh's low-latency unicast transport (no
    batching, no priority queues: QoS off), which every session of a run must share.
    ``tls``: mutual TLS (``TlsCredentials.zenoh``): the session speaks TLS only, and
    its own listener, when none is given, is ``tls/127.0.0.1:0``.
    """
    import zenoh

    if mode not in ("peer", "router", "client"):
        raise ValueError(f"zenoh mode {mode!r}")
    conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    if mode == "router" and not multicast:
        # a router otherwise spends 500 ms scouting for peers before it opens; there are none to find
        conf.insert_json5("scouting/delay", "0")
    if mode == "peer":
        # of two peers that learn of each other, only the one with the greater id opens the link (not both
        # at once): without it 4 of 24 start-ups of a peer run with --low-latency here never saw every peer
        # (and earlier about one in six with passwords); with it 34 of 34 did
        conf.insert_json5("scouting/gossip/autoconnect_strategy",
                          json.dumps({"peer": {"to_router": "always", "to_peer": "greater-zid"}}))
    if mode != "client":
        file_listen = _json_or_none(conf, "listen/endpoints")
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        elif not file_listen:
            conf.insert_json5("listen/endpoints", json.dumps([TLS_LOOPBACK_ANY if tls else LOOPBACK_ANY]))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if mode == "client":  # wait for the router a while (nodes may start in any order), then fail loudly
        conf.insert_json5("connect/timeout_ms", json.dumps(CLIENT_CONNECT_TIMEOUT_MS))
    if mode != "router":
        # a node started a few ms before its router or hub listens connects a few ms later, not at the
        # next 100 ms (a client) or 1 s (a peer: Zenoh's default) retry; then backing off to 1 s
        conf.insert_json5("connect/retry", json.dumps({"period_init_ms": RETRY_INIT_MS, "period_max_ms": 1000,
                                                        "period_increase_factor": 2}))
    # no message of a run is larger than a few kB: a larger one is dropped by Zenoh itself
    conf.insert_json5("transport/link/rx/max_message_size", json.dumps(MAX_MESSAGE_BYTES))
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password or ""))
    if dictionary_file is not None:
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(Path(dictionary_file).resolve())))
    if acl is not None:
        conf.insert_json5("access_control", json.dumps(acl))
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls))
        conf.insert_json5("transport/link/protocols", json.dumps(["tls"]))  # no plain TCP link at all
    if low_latency:
        conf.insert_json5("transport/unicast/lowlatency", "true")
        conf.insert_json5("transport/unicast/qos/enabled", "false")
    return conf


# ============================================================================ credentials
class Credentials:
    """The run's secret: one ``user:password`` line per process (``USERS``), in a 0600 file.

    A router (or a peer that accepts links) authenticates against every line (the
    file is Zenoh's ``dictionary_file``); a process presents its own line.  Made
    fresh for every ``testbed run`` (``Credentials.new``), or once with
    ``testbed secret PATH`` for nodes started by hand, on one host or several.
    """

    def __init__(self, users: dict[str, str]):
        self.users = dict(users)

    @classmethod
    def new(cls, users: Iterable[str] = USERS) -> Credentials:
        import secrets

        return cls({u: secrets.token_urlsafe(24) for u in users})

    @classmethod
    def read(cls, path: str | Path) -> "Credentials":
        """Read and check a secret file: it must be a regular file that only its owner can read."""
        import stat

        from ..common.errors import BadInput

        p = Path(path)
        try:
            st = p.stat()
        except OSError as e:
            raise BadInput(f"secret file {p}: {e.strerror}") from None
        if not stat.S_ISREG(st.st_mode):
            raise BadInput(f"secret file {p}: not a regular file")
        if st.st_mode & 0o077:
            raise BadInput(f"secret file {p}: readable by others (mode {stat.S_IMODE(st.st_mode):o}); "
                           f"chmod 600 {p}")
        if st.st_size > 65536:
            raise BadInput(f"secret file {p}: {st.st_size} bytes is not a secret file")
        users = {}
        try:
            text = p.read_text(encoding="ascii")
        except (OSError, UnicodeDecodeError) as e:
            raise BadInput(f"secret file {p}: {e}") from None
        for n, line in enumerate(text.splitlines(), 1):
            line = line.strip()
            if not line:
                continue
            user, sep, pw = line.partition(":")
            if not sep or not user.strip() or not pw.strip():
                raise BadInput(f"secret file {p}, line {n}: expected user:password")
            users[user.strip()] = pw.strip()
        if not users:
            raise BadInput(f"secret file {p}: empty")
        return cls(users)

    def write(self, path: str | Path) -> Path:
        """Write the secret to a new 0600 file (never overwrites)."""
        import os

        p = Path(path)
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write("".join(f"{u}:{pw}\n" for u, pw in self.users.items()))
        return p

    def password(self, user: str) -> str:
        from ..common.errors import BadInput

        try:
            return self.users[user]
        except KeyError:
            raise BadInput(f"the secret has no line for {user!r} (it has {', '.join(self.users)})") from None

    def only(self, user: str) -> "Credentials":
        return Credentials({user: self.password(user)})


class TlsCredentials:
    """The peer topology's credentials: a key and a certificate per process (``USERS``), in a 0700 folder.

    ``ca.pem`` is the run's own certificate authority; its key signs one certificate
    per process (common name: the process's name, ``USERS``) and is then thrown away,
    so no further certificate of the run can ever be made.  ``NAME.key`` (0600) and
    ``NAME.pem`` are a process's own.  Zenoh's mutual TLS checks that both ends of a
    link hold a certificate of that authority, and its access control reads the
    common name at the other end of every link (``acl_config(..., by="cert_common_names")``).
    """

    VALID_DAYS = 30
    MAX_FILE = 65536

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)

    @classmethod
    def new(cls, folder: str | Path, users: Iterable[str] = USERS) -> TlsCredentials:
        """Make the authority and every process's key and certificate in the new folder ``folder``."""
        import datetime
        import os

        try:
            from cryptography import x509
            from cryptography.hazmat.primitives import hashes, serialization
            from cryptography.hazmat.primitives.asymmetric import ec
            from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
        except ImportError:
            from ..common.errors import BadInput

            raise BadInput("the authenticated peer topology makes TLS certificates with the 'cryptography' "
                           "package, a dependency of dos-testbed: pip install cryptography (or run "
                           "--topology router)") from None
        d = Path(folder)
        d.mkdir(mode=0o700)
        now = datetime.datetime.now(datetime.UTC)
        start, end = now - datetime.timedelta(hours=1), now + datetime.timedelta(days=cls.VALID_DAYS)
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"testbed run authority {os.urandom(6).hex()}")])
        ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
              .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
              .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
              .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                           data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                           crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
              .sign(ca_key, hashes.SHA256()))
        _write_new(d / "ca.pem", ca.public_bytes(serialization.Encoding.PEM), 0o644)
        import ipaddress

        for u in users:
            key = ec.generate_private_key(ec.SECP256R1())
            cert = (x509.CertificateBuilder()
                    .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, u)])).issuer_name(ca_name)
                    .public_key(key.public_key()).serial_number(x509.random_serial_number())
                    .not_valid_before(start).not_valid_after(end)
                    .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                    .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                          ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                    .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost"),
                                                                x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                                   critical=False)
                    .sign(ca_key, hashes.SHA256()))
            _write_new(d / f"{u}.key", key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                         serialization.NoEncryption()), 0o600)
            _write_new(d / f"{u}.pem", cert.public_bytes(serialization.Encoding.PEM), 0o644)
        del ca_key  # never written: the run's authority signs nothing more
        return cls(d)

    def zenoh(self, user: str) -> dict:
        """``transport/link/tls`` of ``user``'s session (checked: BadInput if a file is missing or unsafe)."""
        import stat

        from ..common.errors import BadInput

        files = {"ca": self.folder / "ca.pem", "cert": self.folder / f"{user}.pem", "key": self.folder / f"{user}.key"}
        for what, f in files.items():
            try:
                st = f.stat()
            except OSError as e:
                raise BadInput(f"TLS folder {self.folder}: {f.name}: {e.strerror} (testbed run makes one per run; "
                               f"testbed secret --tls DIR makes one for nodes started by hand)") from None
            if not stat.S_ISREG(st.st_mode) or st.st_size > self.MAX_FILE or st.st_size == 0:
                raise BadInput(f"TLS folder {self.folder}: {f.name} is not a PEM file")
            if what == "key" and st.st_mode & 0o077:
                raise BadInput(f"TLS folder {self.folder}: {f.name} is readable by others "
                               f"(mode {stat.S_IMODE(st.st_mode):o}); chmod 600 {f}")
        ca, cert, key = (str(files[k].resolve()) for k in ("ca", "cert", "key"))
        # the name in a certificate is the identity; which address was dialled is not (nodes move between
        # namespaces and hosts): the authority and the access control by common name decide
        return {"root_ca_certificate": ca, "listen_private_key": key, "listen_certificate": cert,
                "connect_private_key": key, "connect_certificate": cert, "enable_mtls": True,
                "verify_name_on_connect": False}


def require_tls(endpoints: Iterable[str], what: str = "--topology peer") -> None:
    """The peer topology's links are mutual TLS: every endpoint ``tls/HOST:PORT`` (BadInput otherwise)."""
    from ..common.errors import BadInput

    for ep in endpoints:
        if not str(ep).startswith("tls/"):
            raise BadInput(f"{what}: endpoint {ep}: the links are mutual TLS (tls/HOST:PORT)")


def _write_new(path: Path, data: bytes, mode: int) -> None:
    import os

    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


#: roles that may run inside another node's process (``--colocate encoder``: in the plant's)
COLOCATABLE = {"encoder": "plant"}


def colocated_roles(value: str | Iterable[str] | None) -> tuple[str, ...]:
    """``--colocate``'s value (one role, several, or None) as a sorted tuple of roles."""
    return tuple(sorted({value} if isinstance(value, str) else set(value or ())))


def host_of(role: str, colocate: tuple[str, ...] = ()) -> str:
    """The process (user) that runs ``role``: its own, or its host's when colocated."""
    return COLOCATABLE[role] if role in colocate else role


#: the keys (after ``testbed/<run_id>/``) each process may publish on, and its liveliness tokens
def publish_keys(user: str, colocate: tuple[str, ...] = ()) -> list[str]:
    """What ``user`` may publish on; a process that hosts a colocated role also publishes that role's keys."""
    if user in colocate:
        return []  # no process of its own
    guests = [r for r in colocate if COLOCATABLE.get(r) == user]
    return _own_keys(user) + [k for r in guests for k in _own_keys(r)]


def _own_keys(user: str) -> list[str]:
    own = {"plant": ["loop/sensor", "control/start", "control/stop"],
           "encoder": ["loop/symbol/tx"],
           "attacker": ["loop/symbol/rx", "loop/ack/rx", "attacker/status"],
           "controller": ["loop/actuation", "loop/ack/tx"],
           RECORDER: ["recorder/stats"],
           LAUNCHER: ["control/stop", "collector/summaries"]}[user]
    name = COLLECTOR if user == LAUNCHER else user
    if user in ROLES or user == LAUNCHER:
        own += [f"telemetry/{user}", f"events/{user}", f"summary/{user}"] if user in ROLES else \
            [f"events/{user}", f"summary/{user}"]
    return own + [f"alive/{name}", f"ready/{name}"]


def acl_config(keys: Keys, colocate: tuple[str, ...] = (), by: str = "usernames") -> dict:
    """Zenoh access control of the run's router (or of every peer): each process may publish only on its own keys.

    Default deny; every authenticated client may subscribe to and receive everything of
    the run, and put (and declare liveliness tokens, queryables and replies) only on
    ``publish_keys(user)``.  The router accepted every link, so it knows the user name
    at the other end of each and checks every message.  ``by="cert_common_names"`` (the
    peer topology): the remote is known by its certificate on every link, whichever end
    opened it, and every peer checks what it receives.  ``colocate``: roles run inside
    another process (``COLOCATABLE``): their keys move to the host's user, and their own
    user may publish nothing.
    """
    p = keys.prefix
    every = f"{p}/**"
    listen_msgs = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query"]
    pub_msgs = ["put", "liveliness_token", "declare_queryable", "reply"]
    if by not in ("usernames", "cert_common_names"):
        raise ValueError(f"access control by {by!r}")
    subjects = [{"id": u, by: [u]} for u in USERS]
    rules = [{"id": "listen", "messages": listen_msgs, "flows": ["ingress", "egress"], "permission": "allow",
              "key_exprs": [every]},
             {"id": "receive", "messages": listen_msgs + pub_msgs + ["delete"], "flows": ["egress"],
              "permission": "allow", "key_exprs": [every]}]
    own = {u: publish_keys(u, colocate) for u in USERS}
    rules += [{"id": f"publish_{u}", "messages": pub_msgs, "flows": ["ingress"], "permission": "allow",
               "key_exprs": [f"{p}/{k}" for k in own[u]]} for u in USERS if own[u]]
    policies = [{"id": f"policy_{u}", "rules": ["listen", "receive"] + ([f"publish_{u}"] if own[u] else []),
                 "subjects": [u]} for u in USERS]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _json_or_none(conf: Any, key: str) -> Any:
    try:
        v = json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - absent key
        return None
    if isinstance(v, dict):  # per-mode defaults: {"router": [...], "peer": [...]} - not user-set
        return None
    return v


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (for one run's listener)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def endpoint_host(ep: str) -> str:
    """``tcp/10.0.0.1:7447`` -> ``10.0.0.1``."""
    rest = ep.split("/", 1)[-1]
    return rest.rsplit(":", 1)[0].strip("[]")


# QoS of the control path and of telemetry (keyword arguments for declare_publisher)
def control_qos() -> dict:
    import zenoh

    return dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME,
                express=True)


def telemetry_qos() -> dict:
    import zenoh

    return dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA_LOW)
