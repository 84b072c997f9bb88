"""A plant device that does one thing wrong, for the device-fault tests: the bundled plant with one fault.

- ``python faulty_device.py no-stop``: runs every sample, then never sends its Stop (it lingers on, alive);
- ``python faulty_device.py nan-x K``: x_K on ``loop/sensor`` has a non-finite entry (NaN);
- ``python faulty_device.py short-x K``: x_K on ``loop/sensor`` has one entry fewer than the plant's n;
- ``python faulty_device.py late K``: samples x_K 0.2 s late (more than the paper's deadline d T = 50 ms);
- ``python faulty_device.py freeze K``: freezes (SIGSTOP to itself) at sample K and never wakes: to its peers
  a device whose link went down for longer than Zenoh's lease.

Each joins the run of ``$TESTBED_JOIN`` as ``testbed node plant`` does."""

from __future__ import annotations

import os
import signal
import struct
import sys
import threading
import time

from testbed.common.dispatch import run_child
from testbed.nodes.clock import RunClock
from testbed.nodes.plant import PlantNode
from testbed.wire import messages as msg


class _Mute:
    def put(self, *a, **kw) -> None:
        pass


def main(argv: list[str]) -> int:
    fault = argv[0]
    K = int(argv[1]) if len(argv) > 1 else -1
    if fault == "no-stop":
        run = PlantNode.run

        def run_without_stop(self):
            self.pub_stop = _Mute()
            run(self)
            threading.Event().wait()  # alive, and silent, until the test kills it

        PlantNode.run = run_without_stop
    elif fault in ("nan-x", "short-x"):
        encode = msg.Sensor.encode

        def bad_sensor(self):
            if self.k != K:
                return encode(self)
            x = (float("nan"), *self.x[1:]) if fault == "nan-x" else self.x[:-1]
            return struct.pack(f"<{len(x)}d", *x), msg.Header(self.k, self.stamp_ns).encode()

        msg.Sensor.encode = bad_sensor
    elif fault == "late":
        sleep_until = RunClock.sleep_until

        def late(self, t_ns, spin_ns=0, stop=None):
            if t_ns == K * 100_000_000:  # the paper's T = 0.1 s
                t_ns += 200_000_000
            return sleep_until(self, t_ns, spin_ns, stop)

        RunClock.sleep_until = late
    elif fault == "freeze":
        maybe_crash = PlantNode.maybe_crash

        def freeze(self, k):
            if k == K:
                os.kill(os.getpid(), signal.SIGSTOP)
                time.sleep(3600)
            return maybe_crash(self, k)

        PlantNode.maybe_crash = freeze
    else:
        print(f"faulty_device.py: unknown fault {fault!r}", file=sys.stderr)
        return 2
    return run_child(["node", "plant"])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
