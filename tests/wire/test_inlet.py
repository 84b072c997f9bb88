"""The Inlet (``--rx spin``) on a real Zenoh session in this process: every sample handled once, in
order, whether the spinner or the callback takes it; and the spin window it learns from arrivals."""

from __future__ import annotations

import threading
import time
import types

import zenoh

from testbed.nodes.inlet import Inlet

KEY = "testbed/test/inlet"
T_NS = 20_000_000


class _Clock:
    def __init__(self):
        self.t0 = time.monotonic_ns()

    def now(self) -> int:
        return time.monotonic_ns() - self.t0


def _session():
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    return zenoh.open(conf)


def _node(session):
    ctx = types.SimpleNamespace(session=session, clock=_Clock(), T_ns=T_NS, stop=threading.Event())
    return types.SimpleNamespace(ctx=ctx)


def test_every_sample_is_handled_once_in_order_by_the_spinner_or_the_callback():
    with _session() as session:
        node = _node(session)
        got, lock = [], threading.Lock()

        def handler(sample):
            k = int.from_bytes(sample.payload.to_bytes(), "little")
            with lock:
                got.append(k)
            return k

        inlet = Inlet(node, KEY, handler, budget_ns=50_000_000, thread=False)
        pub = session.declare_publisher(KEY)
        n = 30
        for k in range(n):
            pub.put(k.to_bytes(4, "little"), attachment=b"a")
            if k % 2 == 0:  # the node's loop spins for this one (the callback may still be first)
                inlet.spin(node.ctx.clock.now() + 50_000_000)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with lock:
                if len(got) >= n:
                    break
            time.sleep(0.01)
        time.sleep(0.1)  # nothing handled twice after the last one
        assert got == list(range(n))
        assert inlet.spun + inlet.woken == n and not inlet.broken
        node.ctx.stop.set()


def test_the_spin_window_opens_a_margin_before_the_earliest_arrival_and_lasts_the_budget():
    with _session() as session:
        node = _node(session)
        inlet = Inlet(node, KEY + "/w", lambda s: None, budget_ns=2_000_000, margin_ns=300_000, thread=False)
        assert inlet.window(0) is None  # no arrivals yet: no window
        inlet.offsets.extend([1_500_000, 1_200_000, 1_800_000])  # arrivals 1.2-1.8 ms after t_k
        inlet.last_k = 4
        start, end = inlet.window(5 * T_NS)
        assert end - start == 2_000_000
        assert start == 5 * T_NS + 1_200_000 - 300_000  # sample 5: the earliest offset less the margin
        inlet.budget_ns = 0
        assert inlet.window(5 * T_NS) is None  # spinning off
        node.ctx.stop.set()
