"""What a plant device does wrong, as faults of the run: never a hang, never a silent pass.

A plant that is not the testbed's own process (``--external plant``: a device, or any node from outside)
is judged by what it sends.  ``DeviceWatch.tick`` turns each of these into one fault (a named kind, its
sample ``at_sample``, its time ``t_s`` after t0, ``why``), once:

* ``state_nonfinite``, ``state_wrong_length``: an x_k on ``loop/sensor`` with a non-finite entry or a length
  other than the plant's n (the encoder's event of that kind: ``testbed.wire.messages.state_fault``); the
  encoder never encodes it, and the run ends at that sample.  Of any plant, the testbed's own included;
* ``sample_late``: a sample taken (its telemetry's ``t_ns``) more than the deadline d T after its instant
  k T; the loop treats it as it treats any late sample, and the run goes on;
* ``no_stop``: no ``Stop`` from the plant ``NO_STOP_GRACE_S`` after the run's last sample was due; the
  launcher stops the run.
* A device that disconnects (its liveliness token goes before its Stop: it closed its session, or its link
  was down for longer than Zenoh's lease) is the fault ``lost`` (``StallControl.check_lost``); the run ends.

Each is a fault of the launcher's summary, an event of node ``launcher`` in the recording (kind
``plant_<kind>``), one line on stderr, and makes ``testbed run`` exit 1 (``recorder.exit_code``).
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from ..record.faults import Fault
from ..wire import messages as msg
from ..wire.messages import STATE_NONFINITE, STATE_WRONG_LENGTH

if TYPE_CHECKING:
    from .collect import Collector

#: the plant's Stop is due this long after the run's last sample at the latest (the other nodes wait 5 s)
NO_STOP_GRACE_S = 2.0
#: the faults of a device, and which of them end the run
DEVICE_FAULTS = (STATE_NONFINITE, STATE_WRONG_LENGTH, "sample_late", "no_stop", "lost")
ENDS_RUN = (STATE_NONFINITE, STATE_WRONG_LENGTH, "no_stop", "lost")


class DeviceWatch:
    """The launcher's watch over the plant's messages (``external``: the plant is a node from outside)."""

    def __init__(self, start: msg.Start, deadline: float, external: bool):
        self.T_ns, self.N = int(start.T_ns), int(start.n_steps)
        self.deadline_ns = int(deadline * self.T_ns)
        self.external = external
        self.faults: list[Fault] = []
        self._events_seen = 0
        self._k_checked = -1
        self._late = False
        self._no_stop = False

    def _fault(self, kind: str, k: int, t_ns: int | None, why: str) -> Fault:
        f = Fault(role="plant", kind=kind, sample=int(k), time=None if t_ns is None else round(t_ns / 1e9, 4),
                  external=self.external, ends_run=kind in ENDS_RUN, detail=why)
        self.faults.append(f)
        print(f"testbed run: plant fault {kind} at sample {k}: {why}", file=sys.stderr, flush=True)
        return f

    def tick(self, col: Collector, now_ns: int, *, final: bool = False) -> list[Fault]:
        """The new faults (``now_ns``: ns since t0 on the launcher's clock)."""
        n0 = len(self.faults)
        with col.lock:
            evs = col.events[self._events_seen:]
        self._events_seen += len(evs)
        for e in evs:
            if e.node == "encoder" and e.kind in (STATE_NONFINITE, STATE_WRONG_LENGTH) \
                    and not any(f.kind in ENDS_RUN for f in self.faults):
                self._fault(e.kind, e.k, e.k * self.T_ns, e.detail)
        if not self.external:
            return self.faults[n0:]
        for k in range(self._k_checked + 1, col.last_k("plant") + 1):
            t = col.record("plant", k)
            self._k_checked = k
            if t is None or self._late:
                continue
            late = t.t_ns - k * self.T_ns
            if late > self.deadline_ns:
                self._late = True
                self._fault("sample_late", k, t.t_ns, f"sampled {late / 1e6:.1f} ms after its instant k T, beyond the "
                                                      f"deadline d T = {self.deadline_ns / 1e6:g} ms")
        if not self._no_stop and not col.plant_done() and not final \
                and now_ns > self.N * self.T_ns + int(NO_STOP_GRACE_S * 1e9):
            self._no_stop = True
            fin = col.plant_final
            k = fin.k if fin is not None else col.last_k("plant") + 1
            self._fault("no_stop", k, now_ns, f"no Stop from the plant {NO_STOP_GRACE_S:g} s after the run's last "
                                              f"sample was due: the launcher stops the run")
        return self.faults[n0:]

    def ends_run(self) -> Fault | None:
        """The first fault that ends the run, or None."""
        return next((f for f in self.faults if f.ends_run), None)


__all__ = ["DeviceWatch", "DEVICE_FAULTS", "ENDS_RUN", "NO_STOP_GRACE_S"]
