"""``testbed run --netns``: every node process in its own network namespace, joined by veth links
through a bridge, so that every message crosses real network stacks; and ``--cut ROLE@S:D``, a
node's link set down for D seconds and up again.

Topology (nothing is added to the host's own namespace): one namespace per node process (a
colocated encoder shares the plant's), one for the launcher and its recorder (the hub, where the
run's router listens), and one for the bridge (the switch). Each of them but the switch has an
``eth0`` on 10.77.0.0/24, the peer of a port of the switch's bridge ``br0``. The launcher enters
the hub itself (setns, before Zenoh starts a thread) and listens on ``tcp/10.77.0.1:7447``; every
node listens on its own address and connects to the hub's, so the nodes' endpoints are the
bridge's addresses (``--listen``, ``--node-listen``, ``--node-prefix`` are set by ``--netns``).

Names: ``tbn-<launcher pid>-<run id>-<who>``; the switch's ports are ``<who>-<tag>`` (a tag of
the run id: interface names have 15 characters at most). The launcher removes its namespaces at
the end of the run, also after Ctrl-C and after a node crash. A launcher that was SIGKILLed
cannot: the next ``--netns`` run and ``testbed run --netns-clean`` remove every ``tbn-`` namespace
whose launcher pid is gone (its processes, if any are left, are killed first). Removing a
namespace removes its links with it.
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from typing import TYPE_CHECKING

from ..common.errors import BadInput
from ..record.faults import Fault
from .stalls import parse_role_interval

if TYPE_CHECKING:
    from ..nodes.options import RunConfig, RunOptions
    from .faultlog import FaultLog

PREFIX = "tbn-"
NET = "10.77.0"
HUB_PORT = 7447
CLONE_NEWNET = 0x40000000
SHORT = {"hub": "hub", "switch": "sw", "plant": "plant", "encoder": "enc", "attacker": "att", "controller": "ctl"}
#: fault kinds the run rides through (an injected disturbance, not a failure: the exit code stays 0)
RIDDEN_THROUGH = ("link_cut",)
_SAFE = re.compile(r"[^A-Za-z0-9_.]+")


def add_netns_arguments(g: argparse._ActionsContainer) -> None:
    """The flags of ``testbed run`` this module serves (in the ``network`` group)."""
    g.add_argument("--netns", action="store_true",
                   help="every node in its own network namespace, joined by veth links through a bridge "
                        "(root and iproute2's ip); removed at the end")
    g.add_argument("--netns-clean", action="store_true",
                   help="only remove the namespaces of --netns runs whose launcher is gone, then exit")


def add_cut_arguments(g: argparse._ActionsContainer) -> None:
    g.add_argument("--cut", action="append", default=[], metavar="ROLE@SECONDS:DURATION",
                   help="with --netns: set a node's link down SECONDS after t0, up again DURATION seconds later "
                        "(repeatable)")


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], check=check, capture_output=True, text=True, timeout=20)


def privileges_missing() -> str | None:
    """Why ``--netns`` cannot run here (None: it can)."""
    if shutil.which("ip") is None:
        return "iproute2's 'ip' not found"
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_SYS_ADMIN, CAP_NET_ADMIN)"
    return None


def _pid_alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return b"testbed" in f.read()
    except OSError:
        return False


def list_namespaces() -> list[str]:
    r = _ip("netns", "list", check=False)
    return [line.split()[0] for line in r.stdout.splitlines() if line.strip()]


def clean_stale() -> list[str]:
    """Remove the namespaces of ``--netns`` runs whose launcher is gone; returns their names."""
    gone = []
    for ns in list_namespaces():
        if not ns.startswith(PREFIX):
            continue
        pid = ns[len(PREFIX):].split("-", 1)[0]
        if not pid.isdigit() or _pid_alive(int(pid)):
            continue
        for p in _ip("netns", "pids", ns, check=False).stdout.split():  # a node left behind
            try:
                os.kill(int(p), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                pass
        if _ip("netns", "del", ns, check=False).returncode == 0:
            gone.append(ns)
    return gone


def main_clean() -> int:
    """``testbed run --netns-clean``."""
    why = privileges_missing()
    if why:
        raise BadInput(f"--netns-clean: {why}")
    gone = clean_stale()
    print(f"testbed run --netns-clean: removed {len(gone)} namespaces of runs whose launcher is gone"
          + (f": {', '.join(gone)}" if gone else ""))
    return 0


def _parse_cuts(items: list[str], processes: tuple[str, ...], colocated: tuple[str, ...]) -> list[tuple[str, float, float]]:
    cuts = []
    for it in items:
        role, s, d = parse_role_interval(it, "--cut")
        if role in colocated:
            raise BadInput(f"--cut {it}: the {role} runs in another node's process and namespace (--colocate "
                           f"{role}); cut that node's link")
        cuts.append((role, s, d))
    return cuts


class NetnsRun:
    """One run's namespaces: planned from the arguments, made by ``up``, removed by ``down``."""

    def __init__(self, run_id: str, processes: tuple[str, ...], cuts: list[tuple[str, float, float]]):
        self.pid = os.getpid()
        safe = _SAFE.sub("_", run_id)[:100]
        tag = hashlib.sha1(run_id.encode()).hexdigest()[:6]
        self.who = ("hub", *processes)                     # an eth0 each, on the bridge
        self.names = {w: f"{PREFIX}{self.pid}-{safe}-{SHORT[w]}" for w in (*self.who, "switch")}
        self.ports = {w: f"{SHORT[w]}-{tag}" for w in self.who}
        self.addr = {w: f"{NET}.{i}" for i, w in enumerate(self.who, start=1)}
        self.cuts = cuts
        self.cut_state: dict[int, dict] = {}               # index in cuts -> {"down_ns": ..., "up_ns": ...}
        self.created: list[str] = []
        self._home: int | None = None                      # the launcher's own namespace (an fd)

    # ---- the run's arguments
    def endpoints(self, cfg: RunConfig) -> dict:
        """The run's endpoints in the namespaces: ``listen``, ``node_listen`` and ``node_prefix`` of its ``RunConfig``."""
        # mutual TLS links: the peer topology, and the router topology over mutual TLS (--topology router
        # --tls-dir DIR, no --secret-file: the way a zenoh-pico device joins)
        router_tls = cfg.topology == "router" and bool(cfg.tls_dir) and not cfg.secret_file
        scheme = "tls" if (cfg.topology == "peer" or router_tls) and not cfg.insecure else "tcp"
        return {"listen": f"{scheme}/{self.addr['hub']}:{HUB_PORT}",
                "node_listen": {r: f"{scheme}/{self.addr[r]}:0" for r in self.who if r != "hub"},
                "node_prefix": {r: f"ip netns exec {self.names[r]}" for r in self.who
                                if r not in ("hub", cfg.external)}}

    # ---- making and removing
    def up(self) -> None:
        """Remove stale namespaces, make this run's, and move the launcher into the hub."""
        clean_stale()
        try:
            for w in ("switch", *self.who):
                _ip("netns", "add", self.names[w])
                self.created.append(self.names[w])
            sw = self.names["switch"]
            _ip("-n", sw, "link", "add", "br0", "type", "bridge")
            _ip("-n", sw, "link", "set", "br0", "up")
            for w in self.who:
                ns = self.names[w]
                _ip("-n", sw, "link", "add", self.ports[w], "type", "veth", "peer", "name", "eth0", "netns", ns)
                _ip("-n", sw, "link", "set", self.ports[w], "master", "br0")
                _ip("-n", sw, "link", "set", self.ports[w], "up")
                _ip("-n", ns, "addr", "add", f"{self.addr[w]}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", ns, "link", "set", "lo", "up")
            self._enter(self.names["hub"])
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError) as e:
            self.down()
            reason = (getattr(e, "stderr", None) or str(e)).strip().splitlines()
            raise BadInput(f"--netns: cannot make the run's network namespaces: "
                           f"{reason[-1] if reason else e}") from None

    def _enter(self, ns: str) -> None:
        """setns(2) of the calling thread (the launcher's main thread, before Zenoh starts any: the threads
        it starts, and the processes the launcher starts, inherit the namespace)."""
        libc = ctypes.CDLL(None, use_errno=True)
        self._home = os.open("/proc/self/ns/net", os.O_RDONLY)
        fd = os.open(f"/run/netns/{ns}", os.O_RDONLY)
        try:
            if libc.setns(fd, CLONE_NEWNET) != 0:
                raise OSError(ctypes.get_errno(), f"setns into {ns}: {os.strerror(ctypes.get_errno())}")
        finally:
            os.close(fd)

    def down(self) -> None:
        """Back to the launcher's own namespace; remove this run's namespaces (and with them their links)."""
        if self._home is not None:
            ctypes.CDLL(None, use_errno=True).setns(self._home, CLONE_NEWNET)
            os.close(self._home)
            self._home = None
        for ns in reversed(self.created):
            for p in _ip("netns", "pids", ns, check=False).stdout.split():  # a node that outlived the stop
                if p.isdigit() and int(p) != os.getpid():
                    try:
                        os.kill(int(p), signal.SIGKILL)
                    except ProcessLookupError:
                        pass
            r = _ip("netns", "del", ns, check=False)
            if r.returncode != 0:
                print(f"testbed run --netns: could not remove namespace {ns}: {r.stderr.strip()}", file=sys.stderr)
        self.created = []

    # ---- link cuts
    def _link(self, role: str, state: str) -> None:
        _ip("-n", self.names["switch"], "link", "set", self.ports[role], state, check=False)

    def tick(self, faults: FaultLog, now: int | None, t0_mono: int | None) -> None:
        """Start and end the cuts that are due (``now`` None: the run is over, restore every open cut).
        A finished cut is a fault event ``link_cut`` with its interval (s after t0)."""
        if t0_mono is None and now is not None:
            return
        t0 = 0 if t0_mono is None else t0_mono  # read only when ``now`` is given, and then t0_mono is
        for i, (role, sec, dur) in enumerate(self.cuts):
            st = self.cut_state.get(i)
            if now is not None and st is None and now >= t0 + int(sec * 1e9):
                self._link(role, "down")
                self.cut_state[i] = {"down_ns": time.monotonic_ns()}
                print(f"testbed run: link of the {role} cut at {sec:g} s for {dur:g} s", file=sys.stderr)
            elif st is not None and "up_ns" not in st and (now is None or now >= t0 + int((sec + dur) * 1e9)):
                self._link(role, "up")
                st["up_ns"] = time.monotonic_ns()
                base = t0_mono if t0_mono is not None else st["down_ns"] - int(sec * 1e9)
                faults.append(Fault(role=role, kind="link_cut", injected=True,
                                    detail=f"link down for {dur:g} s (--cut {role}@{sec:g}:{dur:g})"
                                           + (" and restored at the end of the run" if now is None else ""),
                                    time=round((st["down_ns"] - base) / 1e9, 4),
                                    down_s=round((st["down_ns"] - base) / 1e9, 4),
                                    up_s=round((st["up_ns"] - base) / 1e9, 4)))


def plan(cfg: RunConfig, run_id: str, opts: RunOptions) -> NetnsRun | None:
    """From ``testbed run``'s ``RunConfig``: this run's namespaces (None without ``--netns``), whose
    ``endpoints`` the launcher then uses; one clear line (``BadInput``) for what cannot be."""
    if not cfg.netns:
        if cfg.cut:
            raise BadInput("--cut needs --netns: it sets the node's veth link down and up (a run over loopback "
                           "has no link of its own to cut)")
        return None
    why = privileges_missing()
    if why:
        raise BadInput(f"--netns: {why}")
    clash = [f for f, v in (("--listen", cfg.listen), ("--node-connect", cfg.node_connect),
                            ("--node-listen", cfg.node_listen), ("--node-prefix", cfg.node_prefix)) if v]
    if clash:
        raise BadInput(f"--netns sets the endpoints itself: drop {', '.join(clash)}")
    return NetnsRun(run_id, opts.processes, _parse_cuts(list(cfg.cut), opts.processes, opts.colocate))
