"""Frozen nodes: ``--stall ROLE@SECONDS:DURATION`` and the watch that notices a stalled node.

A stall is a node that stops (SIGSTOP, a debugger, swapping, a paused VM) and then goes on as if
nothing happened; its liveliness token stays (Zenoh's lease is kept by the peers' transport
until the lease runs out, see docs/live.md "Frozen nodes").  ``StallInjector`` sends SIGSTOP to a
node's process group SECONDS after t0 and SIGCONT DURATION later.  ``StallWatch`` notices a
stall whether injected or not: a node is *behind* when it has fallen more than ``gap`` behind
what drives it (the run clock for the plant and the controller, the plant's samples for the
encoder, the encoder's for the attacker), and the stall is confirmed when the node's own time
stamps jump by more than ``gap`` across it (so a launcher that was itself starved, which sees
everything late, reports nothing).  The interval is read off the node's own stamps: from its
last sample before the stall to its first after, in run time.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import time
from collections.abc import Iterable, Set
from typing import TYPE_CHECKING, Any

from ..common.errors import BadInput
from ..record.faults import Fault
from ..wire import messages as msg
from ..wire import transport

if TYPE_CHECKING:
    import subprocess

    from ..nodes.options import RunConfig
    from .collect import Collector
    from .faultlog import FaultLog
    from .processes import NodeProcesses
    from .spawn import Forked

#: the shortest stall the watch reports (a gap of at least 3 periods, and at least this long)
MIN_GAP_NS = 300_000_000


def parse_role_interval(it: str, flag: str) -> tuple[str, float, float]:
    """One ``ROLE@SECONDS:DURATION`` item (``--stall``, ``--cut``) -> (role, seconds after t0, duration s);
    BadInput naming ``flag`` if malformed."""
    role, at, rest = it.partition("@")
    sec, colon, dur = rest.partition(":")
    try:
        s, d = float(sec), float(dur)
    except ValueError:
        s = d = math.nan
    if not at or not colon or role not in transport.ROLES or not (s >= 0 and d > 0) \
            or not (math.isfinite(s) and math.isfinite(d)):
        raise BadInput(f"{flag} must be ROLE@SECONDS:DURATION with ROLE in {', '.join(transport.ROLES)}, "
                       f"SECONDS >= 0 and DURATION > 0, got {it!r}")
    return role, s, d


def parse_stalls(items: Iterable[str], colocated: Set[str] | tuple[str, ...] = ()) -> dict[str, tuple[float, float]]:
    """``ROLE@SECONDS:DURATION`` items -> {role: (seconds after t0, duration s)}; BadInput if malformed."""
    out = {}
    for it in items:
        role, s, d = parse_role_interval(it, "--stall")
        if role in colocated:
            raise BadInput(f"--stall {it}: the {role} runs inside another node's process (--colocate {role}); "
                           f"a stall freezes a whole process: stall that one, which freezes both")
        out[role] = (s, d)
    return out


def check_fault_times(cfg: RunConfig, n_steps: int, T: float) -> None:
    """Refuse a fault injected where the run never gets (one line, BadInput): ``--kill``, ``--stall`` or
    ``--cut`` at SECONDS at or after the run's end (N T after t0), ``--crash`` at a sample K >= N."""
    end = n_steps * T
    timed = [("--kill", f"{r}@{s:g}", s) for r, s in cfg.kill.items()]
    timed += [(flag, it, parse_role_interval(it, flag)[1]) for flag, items in (("--stall", cfg.stall), ("--cut", cfg.cut))
              for it in items]
    for flag, it, s in timed:
        if s >= end:
            raise BadInput(f"{flag} {it}: {s:g} s is past the run's end ({n_steps} samples, {end:g} s): the fault "
                           f"would never happen (give SECONDS < {end:g}, or a longer --duration)")
    for r, k in cfg.crash.items():
        if k >= n_steps:
            raise BadInput(f"--crash {r}@{k}: sample {k} is past the run's last sample ({n_steps - 1}): the fault "
                           f"would never happen (give K < {n_steps}, or a longer --duration)")


class StallInjector:
    """SIGSTOP to a node's process group at t0 + SECONDS, SIGCONT at t0 + SECONDS + DURATION."""

    def __init__(self, stalls: dict[str, tuple[float, float]]):
        self.stalls = stalls
        self.stopped: dict[str, int] = {}   # role -> monotonic ns of SIGSTOP
        self.resumed: dict[str, int] = {}   # role -> monotonic ns of SIGCONT

    def tick(self, now: int, t0_mono: int, procs: dict) -> None:
        for role, (sec, dur) in self.stalls.items():
            p = procs.get(role)
            if p is None or role in self.resumed:
                continue
            if role not in self.stopped and now >= t0_mono + int(sec * 1e9):
                self.stopped[role] = time.monotonic_ns()
                _signal(p, signal.SIGSTOP)
            elif role in self.stopped and now >= t0_mono + int((sec + dur) * 1e9):
                self.resumed[role] = time.monotonic_ns()
                _signal(p, signal.SIGCONT)

    def release(self, procs: dict) -> None:
        """SIGCONT to every node still stopped (the run ends or is interrupted during a stall)."""
        for role in self.stopped:
            if role not in self.resumed and role in procs:
                self.resumed[role] = time.monotonic_ns()
                _signal(procs[role], signal.SIGCONT)


def _signal(p: subprocess.Popen, sig: int) -> None:
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass


def own_stamp(role: str, t: Any) -> int:
    """When the node handled a telemetry record's sample, on its own clock (ns since t0), or NO_TIME."""
    if role == "plant":
        return t.t_ns
    if role == "encoder":
        return t.rx_ns
    if role == "controller":
        return t.tx_ns
    return t.rx_ns  # attacker


def lateness(role: str, a: Any, t: Any, col: Collector, T_ns: int) -> int | None:
    """How late the node handled sample ``t.k`` (ns), or None: against when it was due (the plant takes
    x_k at t_k; the controller decides it by t_k + c d T < t_k+1), or for the encoder and the attacker
    against when the oldest input it had not handled since its record ``a`` was sent to it (the plant's
    x_j, the encoder's symbol j, for a.k < j <= t.k: it may skip stale ones).  A node that was starved
    of input handles what comes at once: only a frozen node is late.
    """
    if role == "plant":
        return t.t_ns - t.k * T_ns
    if role == "controller":
        return None if t.tx_ns == msg.NO_TIME else t.tx_ns - (t.k + 1) * T_ns
    if t.rx_ns == msg.NO_TIME:
        return None
    up, field = ("plant", "sensor_tx_ns") if role == "encoder" else ("encoder", "tx_ns")
    sent = [getattr(r, field) for j in range(a.k + 1, t.k + 1) if (r := col.record(up, j)) is not None]
    sent = [x for x in sent if x != msg.NO_TIME]
    return t.rx_ns - min(sent) if sent else None


class StallWatch:
    """Notices nodes whose samples stop while their liveliness stays; ``tick`` returns closed stalls as faults."""

    #: what drives each role's samples (None: the run clock)
    UPSTREAM = {"plant": None, "controller": None, "encoder": "plant", "attacker": "encoder"}

    def __init__(self, T_ns: int, n_steps: int, colocated: Set[str] | tuple[str, ...] = ()) -> None:
        self.T_ns, self.N = int(T_ns), int(n_steps)
        self.gap_ns = max(MIN_GAP_NS, 3 * self.T_ns)
        self.gap_k = math.ceil(self.gap_ns / self.T_ns)
        self.colocated = set(colocated)
        self.open: dict[str, tuple] = {}    # role -> (last k before it fell behind, its record)

    def _ref_k(self, role: str, now: int, t0_mono: int, col: Collector) -> int:
        up = self.UPSTREAM[role]
        if up is None:
            return min(self.N - 1, (now - t0_mono) // self.T_ns)
        return col.last_k(up)

    def tick(self, now: int, t0_mono: int, col: Collector, alive: set[str], injected: Set[str] = frozenset(),
             final: bool = False) -> list[Fault]:
        out = []
        for role in transport.ROLES:
            k = col.last_k(role)
            if role not in self.open:
                if not final and role in alive and k >= 0 and self._ref_k(role, now, t0_mono, col) - k > self.gap_k:
                    self.open[role] = (k, col.record(role, k))
                continue
            k0, a = self.open[role]
            if k <= k0 and not final:
                continue
            b = None
            for j in range(k0 + 1, k + 1):  # the first sample it handled late, after the gap
                t = col.record(role, j)
                if t is None:
                    continue
                late = None if a is None else lateness(role, a, t, col, self.T_ns)
                if late is not None and late > self.gap_ns:
                    b = t
                    break
                a = t
            if b is None:
                if not final and self._ref_k(role, now, t0_mono, col) - k > self.gap_k:
                    self.open[role] = (k, a)  # still behind: what came was handled before the gap
                else:
                    del self.open[role]  # it caught up in time (starved of input, or seen late by the launcher)
                continue
            del self.open[role]
            if a is None:
                continue
            ta, tb = own_stamp(role, a), own_stamp(role, b)
            if msg.NO_TIME in (ta, tb):
                continue
            f = Fault(role=role, kind="stalled", from_s=round(ta / 1e9, 4), to_s=round(tb / 1e9, 4),
                      duration_s=round((tb - ta) / 1e9, 4), sample=b.k, last_sample_before=a.k,
                      injected=role in injected,
                      detail=f"no samples for {(tb - ta) / 1e9:.3f} s (samples {a.k} -> {b.k}), then on as before")
            if role == "plant" and "encoder" in self.colocated:
                f.colocated = ["encoder"]
            out.append(f)
        return out


#: a node process whose liveliness token has been gone this long while it runs is lost
LOST_GRACE_NS = 500_000_000


def lost_during(col: Collector, role: str, from_s: float, to_s: float, t0_mono: int | None) -> bool:
    """Whether ``role``'s liveliness token went away between ``from_s`` and ``to_s`` (s after t0) or within
    ``LOST_GRACE_NS`` after: a fault that ended a session (a link cut longer than Zenoh's lease), not a
    token that went at the run's end (docs/live.md, ``liveliness_lost``)."""
    if t0_mono is None:
        return False
    lo = t0_mono + int(from_s * 1e9)
    hi = t0_mono + int(to_s * 1e9) + LOST_GRACE_NS
    with col.lock:
        return any(n == role and not alive and lo <= t <= hi for t, n, alive in col.liveliness)


class StallControl:
    """Inject ``--stall``, watch for stalls and for lost nodes (a node whose liveliness token went while its
    process runs), record them in ``faults``.  ``nodes``: the node processes (their ``procs`` and ``exits``);
    ``external``: the role of a node from outside (the launcher sees only its liveliness)."""

    def __init__(self, stalls: dict[str, tuple[float, float]], colocated: tuple[str, ...], external: str | None,
                 nodes: NodeProcesses, faults: FaultLog):
        """``stalls``: the ``--stall`` items, parsed (``parse_stalls``)."""
        self.inject = StallInjector(stalls)
        self.colocated = colocated
        self.external = external
        self.nodes = nodes
        self.faults = faults
        self.watch: StallWatch | None = None
        self.lost: dict[str, Fault] = {}  # role -> its fault ``lost``

    def check_lost(self, col: Collector, now: int, t0_mono: int) -> None:
        """A node whose liveliness token went while its process runs on (a stall longer than Zenoh's lease,
        a link down): its peers have dropped it, as if it had died; a fault ``lost``, once."""
        if col.plant_done():
            return
        nodes: dict[str, subprocess.Popen | Forked | None] = dict(self.nodes.procs)
        if self.external is not None:  # a node from outside (a device): its liveliness is all the launcher sees
            nodes[self.external] = None
        for role, p in nodes.items():
            lost = col.lost_at(role)
            if role in self.lost or role in self.nodes.exits or lost is None or now - lost < LOST_GRACE_NS \
                    or (p is not None and p.poll() is not None):
                continue
            st = col.start
            assert st is not None  # watched from the start on (t0_mono)
            # one sample and one time: the run's sample at the loss (the plant's controller_lost_at), and
            # separately the last sample the node itself had handled
            k = min(max((lost - t0_mono) // st.T_ns, 0), st.n_steps - 1)
            why = ("its liveliness token went away while its process ran on (frozen for longer than Zenoh's "
                   "lease, or its link down): its peers dropped it") if p is not None else \
                  (f"the external {role} disconnected: its liveliness token went away before the run's end (it "
                   "closed its session, or its link was down for longer than Zenoh's lease)")
            f = Fault(role=role, kind="lost", time=round((lost - t0_mono) / 1e9, 4), sample=int(k),
                      last_sample_before=col.last_k(role), injected=role in self.inject.stopped, detail=why)
            if p is None:
                f.external = True
            self.lost[role] = f
            self.faults.append(f)
            print(f"testbed run: node {role} lost at sample {k} ({f.time:g} s), after its sample "
                  f"{f.last_sample_before}: {f.detail}", file=sys.stderr, flush=True)

    def lost_back(self, col: Collector, t0_mono: int) -> None:
        """When each lost node's liveliness came back, if it did (``back_s``)."""
        with col.lock:
            events = list(col.liveliness)
        for role, f in self.lost.items():
            t_lost = t0_mono + int(f.time * 1e9)
            back = next((t for t, n, alive in events if n == role and alive and t > t_lost), None)
            f.back_s = None if back is None else round((back - t0_mono) / 1e9, 4)

    def tick(self, col: Collector, now: int, t0_mono: int, *, final: bool = False) -> None:
        if not final:
            self.inject.tick(now, t0_mono, self.nodes.procs)
            self.check_lost(col, now, t0_mono)
        if self.watch is None:
            if col.start is None:
                return
            self.watch = StallWatch(col.start.T_ns, col.start.n_steps, self.colocated)
        alive = {r for r in transport.ROLES if r not in self.nodes.exits}
        for f in self.watch.tick(now, t0_mono, col, alive, set(self.inject.stopped), final=final):
            self.faults.append(f)
            print(f"testbed run: node {f.role} stalled from {f.from_s:g} s to {f.to_s:g} s "
                  f"({'injected' if f.injected else 'not injected'}); the run went on", file=sys.stderr, flush=True)

    def release(self) -> None:
        """SIGCONT to every node still stopped by ``--stall``."""
        self.inject.release(self.nodes.procs)

    def end(self, col: Collector, t0_mono: int | None) -> None:
        """At the run's end: resume a node still stopped, and close the stalls that ended."""
        self.release()
        if t0_mono is not None:
            self.tick(col, time.monotonic_ns(), t0_mono, final=True)
            self.lost_back(col, t0_mono)


__all__ = ["check_fault_times", "parse_stalls", "StallInjector", "StallWatch", "StallControl", "lost_during",
           "LOST_GRACE_NS", "MIN_GAP_NS", "own_stamp"]
