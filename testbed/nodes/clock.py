"""The run clock.

Every node agrees on the run's start instant t0, chosen by the plant (the
time master) and published in ``Start.t0_ns`` on CLOCK_REALTIME, the only clock
two hosts can share (keep them in sync with NTP/PTP; the offset between hosts
shifts the controller's loss deadline and the cross-host latency figures).  Each
node converts t0 once into its own CLOCK_MONOTONIC and paces and stamps on that
clock from then on, so a step of the wall clock during a run changes nothing.
On one host (or in network namespaces of one host) the conversion error is a few
microseconds.  All stamps are integer ns since t0; sample k is due at t_k = k T_ns.
"""

from __future__ import annotations

import threading
import time

#: how far ahead of a node's run clock a message's sample instant may be (clock offsets across
#: hosts, a plant that samples a little early); a message for a later sample is rejected
CLOCK_TOLERANCE_NS = 2_000_000


# ============================================================================ clock
class RunClock:
    """ns since t0 on this node's CLOCK_MONOTONIC (t0 given on CLOCK_REALTIME)."""

    def __init__(self, t0_realtime_ns: int):
        self.t0_realtime_ns = int(t0_realtime_ns)
        self.t0_mono_ns = self.t0_realtime_ns - realtime_minus_monotonic()

    def now(self) -> int:
        return time.monotonic_ns() - self.t0_mono_ns

    def sleep_until(self, t_ns: int, spin_ns: int = 0, stop: threading.Event | None = None) -> int:
        """Sleep until ``t_ns`` (ns since t0): sleep to ``t_ns - spin_ns`` then spin; returns now()."""
        target = self.t0_mono_ns + t_ns
        while True:
            rem = target - time.monotonic_ns()
            if rem <= spin_ns:
                break
            if stop is not None and stop.is_set():
                return self.now()
            time.sleep(min((rem - spin_ns) / 1e9, 0.05))
        while time.monotonic_ns() < target:
            pass
        return time.monotonic_ns() - self.t0_mono_ns


def realtime_minus_monotonic() -> int:
    """CLOCK_REALTIME - CLOCK_MONOTONIC in ns (best of a few reads, error ~1 us)."""
    best: tuple[int, int] | None = None
    for _ in range(7):
        a = time.monotonic_ns()
        r = time.time_ns()
        b = time.monotonic_ns()
        if best is None or b - a < best[0]:
            best = (b - a, r - (a + b) // 2)
    assert best is not None
    return best[1]
