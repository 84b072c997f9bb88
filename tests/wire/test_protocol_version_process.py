"""Process tier: a node refuses a run of another wire-protocol version (docs/protocol.md, "Versioning").

The run is crafted by the test: a real Zenoh router session of its own publishes a ``Start`` that
carries another protocol version (and one that carries none) on the run's key; a real
``testbed node`` joins it and must refuse at start-up with one line naming both versions, exit 2.
"""

from __future__ import annotations

import json
import subprocess
import threading

import pytest
from helpers.cli import TIMEOUT, tb_cmd

from testbed.wire import messages as msg
from testbed.wire import transport

pytestmark = pytest.mark.process


@pytest.mark.parametrize("theirs", [msg.PROTOCOL_VERSION + 1, None], ids=["next", "unversioned"])
def test_node_refuses_a_start_of_another_protocol_version(run_id, theirs):
    import zenoh

    keys = transport.Keys.for_run(run_id)
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    start = msg.Start(run_id=run_id, t0_ns=0, T_ns=100_000_000, n_steps=50, digest="0" * 16, timing="ideal",
                      ack_via_attacker=False)
    d = json.loads(start.encode())
    if theirs is None:
        del d["protocol"]  # a Start from before the protocol had a version
    else:
        d["protocol"] = theirs
    crafted = json.dumps(d).encode()
    stop = threading.Event()
    conf = transport.make_config(listen=[ep], mode="router")
    with zenoh.open(conf) as session:
        pub = session.declare_publisher(keys.start)

        def announce():  # as the plant does until t0: a node that joins late gets the next copy
            while not stop.wait(0.05):
                pub.put(crafted)

        th = threading.Thread(target=announce, daemon=True)
        th.start()
        try:
            p = subprocess.run(tb_cmd("node", "controller", "paper", "--insecure", "--run-id", run_id,
                                      "--connect", ep, "--ready-timeout", "60"),
                               capture_output=True, text=True, timeout=TIMEOUT)
        finally:
            stop.set()
            th.join()
    lines = [ln for ln in p.stderr.splitlines() if "INSECURE" not in ln]
    assert p.returncode == 2, p.stderr
    assert lines == [f"testbed node controller: refused: the run speaks protocol version "
                     f"{theirs if theirs is not None else 0}, this node speaks {msg.PROTOCOL_VERSION}"], p.stderr
    assert "Traceback" not in p.stderr
