"""A live run's sessions: its topology, the credentials or certificates made for the run, the
flags that hand them to each process, and the launcher's own session (the run's router)."""

from __future__ import annotations

import ipaddress
import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..common.errors import BadInput
from ..wire import transport
from ..wire.session import AUTO, SessionOptions, zenoh_config

if TYPE_CHECKING:
    from ..nodes.options import RunConfig

#: why ``--topology auto`` chose the peer topology
ONE_HOST = "every node runs on the launcher's host"


def _loopback(ep: str) -> bool:
    """Whether endpoint ``ep`` (``tcp/127.0.0.1:7447``) names this host's loopback (127.0.0.0/8, ::1, localhost)."""
    host = transport.endpoint_host(ep)
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may be another host
        return False


def choose_topology(cfg: RunConfig) -> tuple[str, str]:
    """``--topology``'s topology for the run and why: (``router`` | ``peer``, reason).

    ``auto`` is the peer topology (direct links, mutual TLS: one link per hop instead of two
    through the launcher's router) when every node runs on the launcher's host, and the router
    topology otherwise.  What counts as another host, in this order:

    - ``--tls-dir`` given: the peer topology's certificates, so peer (on any hosts);
    - ``--secret-file`` given: the router topology's password file, so router;
    - ``--node-prefix`` for any node: a node started under a command (``ssh host``, ``ip netns
      exec NS``) runs on another host or in another network namespace;
    - ``--zenoh-config``: its endpoints are the file's, which the launcher does not read;
    - ``--listen``, ``--node-connect`` or ``--node-listen`` naming an address other than loopback
      (127.0.0.0/8, ::1, localhost): an endpoint for processes on other hosts;
    - an authenticated run given a plain ``tcp/`` endpoint (the peer topology's links are TLS).

    None of these: peer.  A given ``--topology router`` or ``peer`` is used as given.
    """
    if cfg.topology != AUTO:
        return cfg.topology, f"--topology {cfg.topology}"
    if cfg.tls_dir:
        return "peer", "--tls-dir: the peer topology's certificates"
    if cfg.secret_file:
        return "router", "--secret-file: the router topology's password file"
    prefixed = list(cfg.node_prefix)
    if prefixed:
        return "router", (f"--node-prefix {', '.join(prefixed)}: a node started under a command runs on another host "
                          "or in another network namespace")
    if cfg.zenoh_config:
        return "router", "--zenoh-config: the file's endpoints may name other hosts"
    given = [("--listen", cfg.listen), ("--node-connect", cfg.node_connect),
             *(("--node-listen", ep) for ep in cfg.node_listen.values())]
    for flag, ep in given:
        if ep and not _loopback(ep):
            return "router", f"{flag} {ep}: not a loopback address (for processes on other hosts)"
    for flag, ep in given:
        if ep and not cfg.insecure and not ep.startswith("tls/"):
            return "router", f"{flag} {ep}: a plain TCP endpoint (the peer topology's links are TLS)"
    return "peer", ONE_HOST


def _start_tls_maker(folder: Path) -> int:
    """Fork a child that makes the run's TLS folder (``TlsCredentials.new``) and exits 0, or 1 if it could not;
    the launcher loads its kernels meanwhile (``Launcher.prewarm``) and never imports ``cryptography``."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            transport.TlsCredentials.new(folder)
            code = 0
        except BaseException:  # noqa: BLE001 - the launcher makes the folder itself and reports why not
            pass
        finally:
            os._exit(code)
    return pid


class RunCredentials:
    """The run's sessions: its topology, its endpoints, and the credentials made for the run or given
    (``cfg``: the run's ``RunConfig``, its endpoints as ``--netns`` set them; ``keys``: the run's key
    space; ``colocated``: the roles that run inside another node's process)."""

    def __init__(self, cfg: RunConfig, run_id: str, keys: transport.Keys, colocated: tuple[str, ...] = ()) -> None:
        self.cfg = cfg
        self.run_id = run_id
        self.keys = keys
        self.colocated = colocated
        self.topology, self.topology_why = choose_topology(cfg)  # --topology auto: peer on one host
        self.secure = not cfg.insecure
        # mutual TLS links (``TlsCredentials``): the peer topology, or the router topology given --tls-dir
        self.tls = self.secure and (self.topology == "peer" or (bool(cfg.tls_dir) and not cfg.secret_file))
        self.listen = cfg.listen or f"{'tls' if self.tls else 'tcp'}/127.0.0.1:{transport.free_port()}"
        self.node_connect = cfg.node_connect or self.listen
        self.node_listen = cfg.node_listen
        self.secret_dir: Path | None = None
        self.secret_path: Path | None = None
        self.tls_dir: Path | None = None              # the peer topology's TLS folder (``make_secrets``)
        self._tls_maker: int | None = None            # the child making the run's certificates

    def check(self) -> None:
        """One clear line (``BadInput``) for credentials that do not fit the topology."""
        if self.tls:
            if self.cfg.secret_file:
                raise BadInput("--secret-file: the peer topology's credentials are TLS certificates (--tls-dir DIR, "
                               "made with 'testbed secret --tls DIR'; by default made for the run)")
            transport.require_tls((self.listen, self.node_connect, *self.node_listen.values()))
        elif self.cfg.tls_dir:
            raise BadInput("--tls-dir with --secret-file: the router topology authenticates by one of them")

    def make_secrets(self, run_dir: Path) -> None:
        """The run's credentials: one password per process, in 0600 files under a 0700 folder; or, for
        mutual TLS, the run's certificates, made by a child process while the launcher goes on
        (``secrets_ready`` waits for them).

        The launcher (the router) keeps the whole dictionary; every process gets a file
        with its own line only.
        """
        if not self.secure:
            return
        if self.tls:
            if self.cfg.tls_dir:
                self.tls_dir = Path(self.cfg.tls_dir).resolve()
                transport.TlsCredentials(self.tls_dir).zenoh(transport.LAUNCHER)  # checked now: one clear line
            else:
                self.secret_dir = Path(tempfile.mkdtemp(prefix="secrets-", dir=run_dir))
                self.tls_dir = self.secret_dir / "tls"
                self._tls_maker = _start_tls_maker(self.tls_dir)
            return
        if self.cfg.secret_file:
            self.secret_path = Path(self.cfg.secret_file).resolve()
            transport.Credentials.read(self.secret_path)  # checked now: one clear line if unusable
            return
        self.secret_dir = Path(tempfile.mkdtemp(prefix="secrets-", dir=run_dir))
        cred = transport.Credentials.new()
        self.secret_path = cred.write(self.secret_dir / "run.secret")
        for u in (*transport.ROLES, transport.RECORDER):
            cred.only(u).write(self.secret_dir / f"{u}.secret")

    def secrets_ready(self) -> None:
        """Once the run's certificates are needed (a process opens a session, a join file names them): wait for
        the child making them; if it failed, make them here, which says why (one clear line)."""
        pid, self._tls_maker = self._tls_maker, None
        if pid is None:
            return
        assert self.tls_dir is not None  # set with the maker (make_secrets)
        _, status = os.waitpid(pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            shutil.rmtree(self.tls_dir, ignore_errors=True)
            transport.TlsCredentials.new(self.tls_dir)
        transport.TlsCredentials(self.tls_dir).zenoh(transport.LAUNCHER)  # checked now: one clear line

    def remove_secrets(self) -> None:
        if self._tls_maker is not None:  # refused or interrupted before they were used
            try:
                os.waitpid(self._tls_maker, 0)
            except ChildProcessError:
                pass
            self._tls_maker = None
        if self.secret_dir is not None:
            shutil.rmtree(self.secret_dir, ignore_errors=True)

    def secret_for(self, who: str) -> Path:
        if self.secret_dir is not None:
            return self.secret_dir / f"{who}.secret"
        if self.secret_path is None:
            raise RuntimeError("secret_for() before make_secrets() of a run with passwords")
        return self.secret_path

    def session_options(self, who: str) -> SessionOptions:
        """The session of process ``who`` (a node or the recorder): the run's topology, its credentials (a file
        path, never the secret itself), the launcher's endpoint and, in the peer topology, its own listener."""
        c = self.cfg
        return SessionOptions(
            run_id=self.run_id, connect=(self.node_connect,), topology=self.topology,
            listen=(self.node_listen.get(who) or self.own_listener(who),) if self.topology == "peer" else (),
            tls_dir=str(self.tls_dir) if self.tls else None,
            secret_file=str(self.secret_for(who)) if self.secure and not self.tls else None,
            insecure=not self.secure, low_latency=c.low_latency,
            zenoh_config=str(Path(c.zenoh_config).resolve()) if c.zenoh_config else None)

    def own_listener(self, who: str) -> str:
        """A peer's listener when ``--node-listen`` names none: loopback for a node, and for the recorder
        (which runs beside the launcher) the launcher's own address, where nodes on other hosts or in
        other network namespaces reach it too."""
        if who == transport.RECORDER:
            scheme = "tls" if self.tls else "tcp"
            host = transport.endpoint_host(self.listen)
            return f"{scheme}/[{host}]:0" if ":" in host else f"{scheme}/{host}:0"
        return transport.TLS_LOOPBACK_ANY if self.tls else transport.LOOPBACK_ANY

    def session_config(self) -> Any:
        """The launcher's own session: the run's router (or a peer), accepting the run's credentials."""
        c = self.cfg
        own = SessionOptions(run_id=self.run_id, listen=(self.listen,), zenoh_config=c.zenoh_config,
                             topology="router" if self.topology == "router" else "peer",
                             tls_dir=None if self.tls_dir is None else str(self.tls_dir),
                             secret_file=None if self.secret_path is None else str(self.secret_path),
                             insecure=not self.secure,
                             low_latency=c.low_latency)
        return zenoh_config(own, transport.LAUNCHER, self.keys, hub=True, colocate=self.colocated)

    def security(self) -> dict:
        from ..wire.session import access_control, transport_security

        given = self.cfg.secret_file or self.cfg.tls_dir
        return {"authenticated": self.secure, "topology": self.topology,
                "topology_auto": self.cfg.topology == AUTO, "topology_why": self.topology_why,
                "low_latency": self.cfg.low_latency,
                "access_control": access_control(self.topology) if self.secure else "none",
                "transport": transport_security(self.topology, not self.secure, self.tls),
                "credentials": None if not self.secure else ("given" if given else "made for the run")}
