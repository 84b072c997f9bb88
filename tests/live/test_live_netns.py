"""Several hosts: the paper's loop across network namespaces joined by veth links.

Topology: one namespace per node (plant, encoder, attacker, controller) plus one
for the launcher, each with an ``eth0`` on 10.77.<net>.0/24, all plugged into a
bridge that lives in a sixth namespace (the "switch").  Nothing is added to the
host's own namespace.  Every node listens on its own address and connects to the
launcher; Zenoh gossip then links the nodes directly across the bridge.
Skipped (with the reason) where namespaces cannot be created (not root, no
iproute2, no CAP_NET_ADMIN, no veth/bridge support), and failed instead where the
capability ``netns`` is required (``TESTBED_REQUIRE``, as CI sets it).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import sys

import pytest
from failclosed import require, rerun_flags, rerun_while_stalled
from helpers.cli import TIMEOUT, run_cli
from helpers.live import BIT_EXACT_KEYS, LOGS, TOPOLOGIES, mismatch, simulate
from helpers.procs import reap

from testbed.wire.transport import ROLES

pytestmark = pytest.mark.process



def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=20)


@pytest.fixture
def netns():
    if os.geteuid() != 0:
        require("netns", "network namespaces need root (CAP_SYS_ADMIN, CAP_NET_ADMIN)")
    if shutil.which("ip") is None:
        require("netns", "network namespaces need iproute2 ('ip' not found)")
    tag = secrets.token_hex(3)
    net = 1 + int(tag, 16) % 250
    names = {r: f"tb{tag}-{r[:4]}" for r in ("hub", *ROLES)}
    switch = f"tb{tag}-sw"
    addr = {r: f"10.77.{net}.{i}" for i, r in enumerate(names, start=1)}
    created: list[str] = []

    def cleanup():
        for ns in reversed(created):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)

    try:
        for ns in (switch, *names.values()):
            _ip("netns", "add", ns)
            created.append(ns)
        _ip("-n", switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", switch, "link", "set", "br0", "up")
        for i, (role, ns) in enumerate(names.items(), start=1):
            _ip("-n", switch, "link", "add", f"p{i}", "type", "veth", "peer", "name", "eth0", "netns", ns)
            _ip("-n", switch, "link", "set", f"p{i}", "master", "br0")
            _ip("-n", switch, "link", "set", f"p{i}", "up")
            _ip("-n", ns, "addr", "add", f"{addr[role]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        if shutil.which("ping"):
            _ip("netns", "exec", names["plant"], "ping", "-c", "1", "-W", "2", addr["controller"])
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError) as e:
        cleanup()
        reason = getattr(e, "stderr", None) or str(e)
        require("netns", f"cannot build network namespaces with veth links here: {reason.strip()}")
    try:
        yield names, addr
    finally:
        cleanup()
        left = [ns for ns in created if ns in subprocess.run(["ip", "netns", "list"], capture_output=True,
                                                             text=True).stdout]
        assert not left, f"namespaces left behind: {left}"


def _run_in_namespaces(names, addr, run_id, topology=(), more=()):
    port = 7447
    scheme = "tls" if "peer" in topology else "tcp"
    cmd = ["ip", "netns", "exec", names["hub"], sys.executable, "-m", "testbed.cli", "run", "paper",
           "--duration", "5", "--json", "--run-id", run_id, "--listen", f"{scheme}/{addr['hub']}:{port}",
           "--run-dir", os.path.join(LOGS, run_id), *topology, *more]
    for r in ROLES:
        cmd += ["--node-prefix", f"{r}=ip netns exec {names[r]}", "--node-listen", f"{r}={scheme}/{addr[r]}:0"]
    try:
        rc, out, err = run_cli(cmd, TIMEOUT)
    finally:
        left = reap(run_id)
    assert not left, f"orphans: {left}"
    return rc, json.loads(out), err


@pytest.mark.parametrize("topology", TOPOLOGIES + [pytest.param(("--topology", "peer"), id="peer")])
def test_paper_across_network_namespaces(netns, topology):
    """Router (the default across namespaces): every node a client of the launcher's router.  Peer: every
    process links to every other across the bridge, mutual TLS with the run's certificates (which name
    processes, not addresses)."""
    names, addr = netns
    run_id = f"t{os.getpid()}xnetns{secrets.token_hex(3)}"
    # the one rerun policy: a stalled run is run again, the last run is compared whatever it reports
    rc, s, err = rerun_while_stalled(lambda n: _run_in_namespaces(names, addr, run_id + "r" * n, topology, rerun_flags(n)),
                                     "netns run")
    assert rc == 0, (s["faults"], err[-3000:])
    # every node process ran in its own network namespace (a colocated encoder in the plant's)
    netns_ids = {r: s["node_summaries"][r]["netns"] for r in ROLES}
    colocated = "--colocate" in topology
    assert len(set(netns_ids.values())) == (3 if colocated else 4), netns_ids
    assert (netns_ids["encoder"] == netns_ids["plant"]) == colocated
    assert s["security"]["transport"] == ("mutual tls" if "peer" in topology else "user/password")
    # the default (--topology auto) counts a node under --node-prefix as on another host: the router topology
    assert s["security"]["topology_auto"] == ("--topology" not in topology)
    if "--topology" not in topology:
        assert s["security"]["topology"] == "router" and "--node-prefix" in s["security"]["topology_why"]
    assert os.readlink("/proc/self/ns/net") not in netns_ids.values()
    sim = simulate("paper", 5)
    for key in BIT_EXACT_KEYS:
        assert s[key] == sim[key], mismatch(s, sim, key)
    # the recorder, beside the launcher, got every node's telemetry across the bridge
    from testbed.record import reader

    rec = reader.read(s["recording"]["path"])
    assert s["recording"]["complete"] and not rec.truncated
    for r in ROLES:
        assert sorted(rec.telemetry[r]) == list(range(s["samples"])), r
