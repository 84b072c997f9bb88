"""A deliberately broken external node for the conformance tests: the bundled node with one fault.

- ``python broken_node.py byte-order``: a plant that publishes x_k on ``loop/sensor`` big-endian (the
  spec says little-endian); its telemetry stays right;
- ``python broken_node.py takes-late``: a plant that keeps an actuation of a sample already past (a
  duplicated or a late copy) for the next sample it has no u for (the spec: ignore it);
- ``python broken_node.py late-stop ROLE``: the bundled ROLE, which answers the run's Stop 8 s late (it
  lingers before it closes its session).

Each joins the run of ``$TESTBED_JOIN`` as ``testbed node ROLE`` does."""

from __future__ import annotations

import struct
import sys
import time

from testbed.common.dispatch import run_child
from testbed.nodes.context import NodeContext
from testbed.wire import messages as msg


def _big_endian_sensor(self):
    return struct.pack(f">{len(self.x)}d", *self.x), msg.Header(self.k, self.stamp_ns).encode()


def main(argv: list[str]) -> int:
    fault, role = argv[0], (argv[1] if len(argv) > 1 else "plant")
    if fault == "byte-order":
        msg.Sensor.encode = _big_endian_sensor
    elif fault == "takes-late":
        from testbed.nodes.plant import PlantNode

        on_actuation = PlantNode._on_actuation

        def takes_late(self, sample):
            try:
                a = msg.Actuation.decode(sample.payload, sample.attachment)
            except msg.MessageError:
                return on_actuation(self, sample)
            if a.k != msg.WARMUP_K and a.k < self._waiting_k:  # kept for the next sample without a u (no checks)
                with self._lock:
                    j = self._waiting_k
                    while j in self._acts:
                        j += 1
                    self._acts[j] = (msg.Actuation(j, a.stamp_ns, a.theta, a.u, a.last_rx), time.monotonic_ns())
                    if j == self._waiting_k:
                        self._got.set()
                return j
            return on_actuation(self, sample)

        PlantNode._on_actuation = takes_late
    elif fault == "late-stop":
        close = NodeContext.close

        def late_close(self):
            time.sleep(8.0)
            close(self)

        NodeContext.close = late_close
    else:
        print(f"broken_node.py: unknown fault {fault!r}", file=sys.stderr)
        return 2
    return run_child(["node", role])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
