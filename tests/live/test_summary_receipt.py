"""A node's summary reaches the launcher before the node closes its session: the node asks the collector
(``collector/summaries``) until its summary is held there; a node that exited cleanly without its summary in
is the fault ``summary_missing``.  Real Zenoh sessions over mutual TLS under the run's access rules: the
launcher's and a node's, in either topology."""

from __future__ import annotations

import subprocess
import time
from types import SimpleNamespace

import pytest

from testbed.live.collect import Collector
from testbed.live.faultlog import FaultLog
from testbed.live.launcher import declare_summaries_held
from testbed.live.processes import NodeProcesses
from testbed.nodes.context import NodeContext, _roles_held
from testbed.nodes.options import RunOptions, load_scenario
from testbed.wire import messages as msg
from testbed.wire import transport


def _until(cond, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


@pytest.mark.slow  # real Zenoh sessions (about a second)
@pytest.mark.parametrize("topology", ["router", "peer"])  # peer: the node checks the launcher's reply too
def test_a_node_closes_once_the_collector_holds_its_summary_and_a_missing_one_is_a_fault(tmp_path, topology):
    import zenoh

    from testbed.wire.session import SessionOptions, zenoh_config

    tls = transport.TlsCredentials.new(tmp_path / "tls")
    keys = transport.Keys.for_run("receipt")
    ep = f"tls/127.0.0.1:{transport.free_port()}"
    opts = RunOptions()
    sc = load_scenario("paper", opts)

    def args(**kw):
        return SessionOptions(topology=topology, tls_dir=str(tls.folder), **kw)

    with zenoh.open(zenoh_config(args(listen=(ep,)), transport.LAUNCHER, keys, hub=True)) as launcher, \
            zenoh.open(zenoh_config(args(connect=(ep,)), "plant", keys)) as node:
        col = Collector(launcher, keys, sc.n_steps)
        held = declare_summaries_held(launcher, keys, col)
        token = launcher.liveliness().declare_token(keys.alive(transport.COLLECTOR))
        ctx = NodeContext("plant", node, sc, opts, keys)
        assert _until(lambda: transport.COLLECTOR in ctx.alive)

        t = time.monotonic()
        assert not ctx.summary_received(["plant"], timeout=0.5)  # not published yet: asked until the timeout
        assert time.monotonic() - t >= 0.5

        # the launcher's end of run: the plant exited cleanly, its summary not in yet
        done = subprocess.Popen(["true"])
        done.wait(10)
        procs = NodeProcesses(run_dir=tmp_path, processes=("plant",), colocated=(), process_of=lambda r: r,
                              node_prefix={}, fork=False, external=None, command=lambda r: [], faults=FaultLog())
        procs.procs["plant"], procs.exits["plant"] = done, {"exit_code": 0}
        procs.wait_summaries(col, timeout=0.1, telemetry_timeout=0.1)
        procs.check_summaries(col)
        assert list(procs.faults) == []  # no run started (a start-up timeout): no summary is due
        start = msg.Start(run_id=keys.run_id, t0_ns=1, T_ns=ctx.T_ns, n_steps=sc.n_steps, digest=ctx.digest,
                          timing="ideal", ack_via_attacker=False)
        node.put(keys.start, start.encode())  # the plant's Start: the run has begun
        assert _until(lambda: col.start is not None)
        procs.check_summaries(col)
        assert [(f.role, f.kind) for f in procs.faults] == [("plant", "summary_missing")]

        ctx.publish_summary({"samples": 3})
        assert ctx.summary_received(["plant"], timeout=20)  # the reply comes after the summary reached it
        assert col.snapshot_summaries() == {"plant": {"samples": 3}}
        procs.faults = FaultLog()
        procs.wait_summaries(col, timeout=5, telemetry_timeout=0.1)
        procs.check_summaries(col)
        assert list(procs.faults) == []

        token.undeclare()  # the launcher gone: nobody to confirm, no wait
        assert _until(lambda: transport.COLLECTOR not in ctx.alive)
        t = time.monotonic()
        assert not ctx.summary_received(["plant", "encoder"], timeout=30)
        assert time.monotonic() - t < 10
        held.undeclare()


def _reply(raw: bytes | None) -> SimpleNamespace:
    """A reply as ``_roles_held`` reads it: ``ok`` (None for an error reply) with its payload's bytes."""
    return SimpleNamespace(ok=None if raw is None else SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: raw)))


@pytest.mark.parametrize("raw,roles", [
    (b'["plant", "encoder"]', {"plant", "encoder"}),
    (b'["plant", 3, null]', {"plant"}),
    (b'{"plant": 1}', set()),
    (b"not json", set()),
    (b"\xff\xfe", set()),
    (b'["' + b"p" * 2000 + b'"]', set()),   # over the bound: not parsed
    (None, set()),                           # an error reply
])
def test_a_reply_is_read_as_a_bounded_list_of_names(raw, roles):
    assert _roles_held(_reply(raw)) == roles
