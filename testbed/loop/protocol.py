"""The loop's protocol state machines: encoder, controller and plant.

Pure: no clock, no network, no threads, no locks.  The live nodes
(``testbed.nodes``) call them from thin shells that own the clock, the waits and
the publishing; the per-sample simulator (``testbed.sim.loop.simulate_loop``)
calls the very same objects with a simulated network, so whatever a live node
decides can be reproduced in-process (``testbed resimulate``).

* ``EncoderProtocol``: Algorithm 1 on x_k, and the ack protocol.  The encoder
  applies (xi), (E) for sample k when it learns theta_k.  If x_{k+1} arrives while
  theta_k is still unknown (a lost or late ack) it sends *nothing* for k+1 and for
  every later sample until theta_k is known: the decoder, receiving nothing, sets
  theta = 1 for those samples, which the encoder can then replay without asking.
  theta_k itself is recovered from any later ack (``last_rx``).  A missing ack
  costs samples, never lockstep.
* ``ControllerProtocol``: Algorithm 2 and control law (2).  Samples are decided
  strictly in order (with ``defer_update`` the decoder's update (xi), (E) of the last
  decision waits for ``settle``, so that the shell sends u_k first; nothing else changes): when the
  symbol arrives (theta_k = 0; an invalid payload
  is a loss, theta_k = 1), when the loss deadline passes with nothing (theta_k = 1),
  or when a later sample's symbol arrives first (the earlier ones are lost).  A
  symbol for a sample already decided is late and ignored; a symbol whose header
  names a sample whose instant has not come yet cannot be genuine and is rejected.
* ``PlantProtocol``: what acts on the true plant over [t_k, t_k+1): the input
  check (a non-finite u is rejected, |u| is clamped to u_max), the hold of
  u_{k-1} for the actuation delay delta_k (physical timing) and the fallback to
  u = 0 after the deadline when u_k never came.
* ``OdeProcess``: a true plant given by its right-hand side, advanced by the flow
  map.  (An FMU plant is another process with the same members.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import numpy.typing as npt

from ..methods.base import DecoderEnd, EncoderEnd, symbol_code
from .flow import DEFAULT_FLOW, FLOW_OK, FlowOptions, compiled_for, flow_into
from .params import corrupt_payload
from .quantizer import Codebook, InvalidSymbol

if TYPE_CHECKING:
    from plants.base import Plant, PlantProcess

    from .device import Device


def _state(end: object) -> Any:
    """A method end's shared state (``methods.End.state``: xi_k and E_k unless the method says otherwise),
    or None for an object that keeps none (the kernel's bookkeeping encoder, ``sim.trajectory._Ledger``)."""
    f = getattr(end, "state", None)
    return None if f is None else np.array(f(), dtype=np.float64)


class MethodFault(Exception):
    """A method's end raised at sample ``k``: the run ends there (``testbed simulate`` and a live node alike).

    ``line`` is what every reader says (:func:`method_fault_line`); ``role`` the node whose end raised
    ("encoder" or "controller")."""

    def __init__(self, method_name: str, k: int, error: BaseException, role: str):
        self.k, self.role, self.error = int(k), role, error
        self.line = method_fault_line(method_name, k, error)
        super().__init__(self.line)


def method_fault_line(method_name: str, k: int, error: BaseException) -> str:
    """The one line of a method fault: ``method 'NAME' raised at sample k: Error: message``."""
    return f"method {method_name!r} raised at sample {int(k)}: {type(error).__name__}: {error}"


# controller decision reasons (the telemetry's ``reason`` field)
RECEIVED = 0
DEADLINE = 1
INVALID = 2
SUPERSEDED = 3
REASONS = {RECEIVED: "received", DEADLINE: "deadline", INVALID: "invalid", SUPERSEDED: "superseded"}


# ============================================================================ encoder
@dataclass(frozen=True)
class Send:
    """The encoder sends ``symbol`` for sample k (xi, E: the state it was encoded with)."""

    k: int
    symbol: int | bytes | bytearray   # a code, or a method's own bytes
    saturated: bool
    xi: np.ndarray
    E: float
    q: np.ndarray
    state: np.ndarray | None = None   # a method's shared state (``EncoderEnd.state``), for the lockstep check


@dataclass(frozen=True)
class Withhold:
    """The encoder sends nothing for sample k (theta of an earlier sample is unknown).

    ``first``: this sample starts a new withholding episode.  ``pending``: the sample
    whose theta is unknown.
    """

    k: int
    first: bool
    pending: int


def skip_sample(enc: EncoderEnd) -> None:
    """theta_k = 1 for a sample whose symbol was never sent (the decoder cannot have it).

    Rules (xi), (E) with theta_k = 1 depend on neither x_k nor the symbol.
    """
    enc.encode(enc.xi)
    enc.ack(1)


class EncoderProtocol:
    """Algorithm 1 and the ack protocol (see the module docstring)."""

    def __init__(self, enc: EncoderEnd, n_steps: int):
        self.enc = enc
        self.n_steps = int(n_steps)
        self.next_k = 0                    # next sample index expected from the plant
        self.pending: int | None = None    # sample sent whose theta is unknown
        self.silent: list[int] = []        # samples withheld while ``pending`` is unresolved
        self.n_sent = 0
        self.n_silent = 0
        self.stale_sensor = 0
        self.stale_acks = 0
        self.inconsistent_acks = 0
        self.desync_episodes = 0

    def _mark_silent(self, j: int) -> None:
        if self.pending is None:
            skip_sample(self.enc)
        else:
            self.silent.append(j)

    def _resolve(self, theta: int) -> None:
        self.enc.ack(theta)
        self.pending = None
        for _ in self.silent:
            skip_sample(self.enc)
        self.silent.clear()

    def sensor(self, k: int, x: npt.ArrayLike) -> Send | Withhold | None:
        """x_k arrived (after the shell's grace for a late ack, if one was pending).

        Returns what to send, or None for a stale or out-of-range sample (counted).
        """
        if k < self.next_k or k >= self.n_steps:
            self.stale_sensor += 1
            return None
        for j in range(self.next_k, k):  # sensor samples that never came: nothing was sent
            self._mark_silent(j)
            self.n_silent += 1
        self.next_k = k
        if self.pending is not None:
            first = not self.silent
            if first:
                self.desync_episodes += 1
            self.silent.append(k)
            self.n_silent += 1
            self.next_k = k + 1
            return Withhold(k, first, self.pending)
        enc = self.enc
        xi, E = enc.xi, enc.E
        state = _state(enc)
        i, sat = enc.encode(np.asarray(x, dtype=np.float64))
        self.pending = k
        self.next_k = k + 1
        self.n_sent += 1
        return Send(k, i if isinstance(i, (bytes, bytearray)) else int(i), bool(sat), xi, E, enc.q, state)

    def ack(self, k: int, theta: int, last_rx: int) -> str:
        """The controller's ack of sample k.  Returns what it did:

        ``"resolved"`` (theta of the pending sample), ``"resync"`` (recovered from a
        later sample's ack), ``"skipped"`` (samples whose x never reached the encoder),
        ``"stale"`` (nothing to do; counted).
        """
        p = self.pending
        if p is None:
            if self.next_k <= k < self.n_steps:
                # theta for samples whose x never reached us: the decoder lost them too
                if theta != 1:
                    self.inconsistent_acks += 1
                for _ in range(self.next_k, k + 1):
                    skip_sample(self.enc)
                    self.n_silent += 1
                self.next_k = k + 1
                return "skipped"
            self.stale_acks += 1
            return "stale"
        if k == p:
            self._resolve(int(theta))
            return "resolved"
        if k > p:
            self._resolve(0 if last_rx == p else 1)
            return "resync"
        self.stale_acks += 1
        return "stale"

    def counters(self) -> dict:
        return {"sent": self.n_sent, "withheld": self.n_silent, "saturations": self.enc.saturations,
                "desync_episodes": self.desync_episodes, "stale_sensor": self.stale_sensor,
                "stale_acks": self.stale_acks, "inconsistent_acks": self.inconsistent_acks}


# ============================================================================ controller
@dataclass(frozen=True)
class Decision:
    """The controller's decision for sample k: u_k, theta_k and the ack's last_rx.

    xi, E: the decoder's state the decision was made with (before the update).
    """

    k: int
    theta: int
    u: np.ndarray
    q: np.ndarray
    xi: np.ndarray
    E: float
    symbol: int        # the code received (-1: none)
    reason: int        # RECEIVED, DEADLINE, INVALID or SUPERSEDED
    last_rx: int
    state: np.ndarray | None = None   # a method's shared state (``DecoderEnd.state``) before the decision


class ControllerProtocol:
    """Algorithm 2 and control law (2), samples decided strictly in order.

    ``defer_update``: a decision leaves the decoder's update (xi), (E) pending until
    ``settle()`` (or the next decision, which settles it first), so that u_k goes out
    before the prediction phi_T(q_k, u_k) is computed.  The numbers are the same.
    """

    def __init__(self, dec: DecoderEnd, n_steps: int, defer_update: bool = False):
        self.dec = dec
        self.defer_update = bool(defer_update)
        self._unsettled = False
        self.codebook: Codebook = dec.codebook
        self.n_steps = int(n_steps)
        self.next_k = 0
        self.last_rx = -1
        self.received = 0
        self.lost_deadline = 0
        self.invalid = 0
        self.late = 0
        self.superseded = 0
        self.future = 0

    def settle(self) -> None:
        """Apply the decoder's update (xi), (E) of the last decision, if it is still pending."""
        if self._unsettled:
            self._unsettled = False
            self.dec.commit()

    def _decide(self, k: int, symbol: int | None, reason: int) -> Decision:
        self.settle()
        dec = self.dec
        xi, E = dec.xi, dec.E
        state = _state(dec)
        u, q, theta = dec.decide(symbol)
        if self.defer_update:
            self._unsettled = True
        else:
            dec.commit()
        if theta == 0:
            self.last_rx = k
        self.next_k = k + 1
        return Decision(k, int(theta), u, q, xi, E, symbol_code(symbol), reason, self.last_rx, state)

    def symbol(self, k: int, payload: bytes, newest_k: int | None = None) -> list[Decision]:
        """The symbol of sample k arrived; the decisions it makes, in order (maybe none).

        ``newest_k``: the newest sample whose instant t_k has come on the run clock (the
        shell computes it); a header naming a later sample is rejected (``future``).
        """
        if k < self.next_k or k >= self.n_steps:
            self.late += 1
            return []
        if newest_k is not None and k > newest_k:
            self.future += 1
            return []
        out = []
        while self.next_k < k:  # a later sample arrived first: the earlier ones are lost
            self.superseded += 1
            out.append(self._decide(self.next_k, None, SUPERSEDED))
        try:
            sym = self.codebook.unpack(payload)
        except InvalidSymbol:
            self.invalid += 1
            out.append(self._decide(k, None, INVALID))
            return out
        self.received += 1
        out.append(self._decide(k, sym, RECEIVED))
        return out

    def deadline(self, k: int) -> Decision | None:
        """Nothing came for sample k by its loss deadline: theta_k = 1 (None if k is not next)."""
        if k != self.next_k or k >= self.n_steps:
            return None
        self.lost_deadline += 1
        return self._decide(k, None, DEADLINE)

    def counters(self) -> dict:
        return {"received": self.received, "lost_deadline": self.lost_deadline, "invalid": self.invalid,
                "late": self.late, "superseded": self.superseded, "future": self.future,
                "overflows": self.dec.overflows, "decided": self.next_k}


# ============================================================================ plant
class OdeProcess:
    """A true plant given by its right-hand side: x advanced by the flow map phi_dt(x, u)."""

    def __init__(self, plant: Plant, flow: FlowOptions = DEFAULT_FLOW):
        self.plant = plant
        self.flow = flow
        self.n, self.m = plant.n, plant.m
        self._x = np.zeros(plant.n)
        self._call: Callable[..., int] | None = None  # the flow map phi_dt of one state (``flow_into``), set on the first advance

    def reset(self, x0: npt.ArrayLike) -> None:
        self._x = np.array(x0, dtype=np.float64)

    def advance(self, u: npt.ArrayLike, dt: float) -> int:
        """Hold u for dt seconds; returns the FLOW_* status (x stays finite).

        phi_dt(x, u) by ``flow_into``, the kernel ``phi_T`` runs for each state of a batch, called
        straight (no batch arrays, no type dispatch): the same numbers, a fraction of the cost.
        """
        if dt <= 0.0:
            return FLOW_OK
        u = np.ascontiguousarray(u, dtype=np.float64).reshape(self.m)
        if self._call is None:
            plant = self.plant
            self._rhs, self._p, self._opts = type(plant).rhs.cfunc, plant.p, self.flow.as_array()
            self._K, self._ytmp = np.empty((13, self.n)), np.empty(self.n)
        out = np.empty(self.n)
        args = (self._rhs, self._x, u, self._p, float(dt), self._opts, self._K, self._ytmp, out)
        if self._call is None:
            st = flow_into(*args)
            self._call = compiled_for(flow_into, args)
        else:
            st = self._call(*args)
        self._x = out
        return int(st)

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    def perturb(self, w: npt.ArrayLike) -> None:
        """x <- x + w (a process disturbance, ``[plant.disturbance]``)."""
        self._x = self._x + np.asarray(w, dtype=np.float64)

    def close(self) -> None:
        pass


@dataclass
class PlantProtocol:
    """Hold, delay and fallback: what acts on the plant over [t_k, t_k+1).

    timing ``ideal``: u_k acts on the whole period (u = 0 if it never came).
    timing ``physical``: u_{k-1} is held for delta_k, then u_k acts:
      actuation ``arrival``: delta_k is when u_k arrived;
      actuation ``scheduled``: a received sample's u_k acts at t_k + delta_s (or on
      arrival if later), a lost sample's u_k = 0 at the deadline t_k + d T.
    If u_k never came by the deadline d T, u_{k-1} is held until then and the actuator
    falls back to 0.  Delays are whole nanoseconds (as the live plant measures them).
    """

    process: PlantProcess
    T: float
    timing: str = "ideal"
    actuation: str = "scheduled"
    sched_ns: int = 0               # delta_s: a received sample's scheduled actuation delay
    deadline_ns: int = 0            # d T
    loss_ns: int = 0                # the controller's loss deadline (a lost sample's u_k leaves then)
    u_max: float = math.inf         # actuator limit: |u| is clamped to it
    u_held: np.ndarray = field(default=None)  # type: ignore[arg-type]  # zeros(m), set after init
    rejected_nonfinite: int = 0
    clamped: int = 0
    device: Device | None = None    # the sensor, actuator and disturbance (``testbed.loop.device.Device``), or None
    u_applied: np.ndarray | None = None  # the input that acted last (after the actuator)

    def __post_init__(self) -> None:
        if self.u_held is None:
            self.u_held = np.zeros(self.process.m)

    @classmethod
    def for_scenario(cls, sc: Any, process: PlantProcess) -> PlantProtocol:  # sc: a Scenario (a layer above)
        phys, sched, s_ns, d_ns, loss_ns = (int(v) for v in sc.timing_params)
        dev = sc.plant.device
        return cls(process, sc.T, timing=sc.run.timing, actuation=sc.run.actuation, sched_ns=s_ns,
                   deadline_ns=d_ns, loss_ns=loss_ns, u_max=sc.controller.u_max,
                   device=None if dev is None else dev.make(process.n, process.m, sc.T))

    def measure(self, k: int, x: np.ndarray) -> np.ndarray:
        """x_meas,k: what the sensor reads of x_k (``[plant.sensor]``; x_k itself without one)."""
        return x if self.device is None else self.device.measure(k, x)

    def check_input(self, u: npt.ArrayLike) -> tuple[np.ndarray | None, str | None]:
        """u_k past the safety check (``[controller] u_max``, before the actuator's own limits):
        (u, None), (clamped u, "clamped") or (None, "nonfinite")."""
        u = np.asarray(u, dtype=np.float64)
        if not np.all(np.isfinite(u)):
            self.rejected_nonfinite += 1
            return None, "nonfinite"
        if np.any(np.abs(u) > self.u_max):
            self.clamped += 1
            return np.clip(u, -self.u_max, self.u_max), "clamped"
        return u, None

    def delay_ns(self, arrival_ns: int, theta: int) -> int:
        """delta_k [ns] of a u_k that reached the plant ``arrival_ns`` after t_k (<= the deadline)."""
        a = min(max(int(arrival_ns), 0), self.deadline_ns)
        if self.actuation == "scheduled":
            return max(a, self.sched_ns if theta == 0 else self.deadline_ns)
        return a

    def step(self, u: np.ndarray | None, delay_ns: int = 0) -> int:
        """Advance over one period.  ``u``: u_k, or None if it never came (then ``delay_ns`` is the
        time until the deadline).  Physical timing only uses ``delay_ns``.  Returns the status."""
        proc = self.process
        m = proc.m
        dev = self.device
        u_k = np.zeros(m) if u is None else np.asarray(u, dtype=np.float64)
        if dev is not None:  # the actuator's physics acts on what arrived (zeros when nothing did)
            u_k = dev.actuate(u_k)
        self.u_applied = u_k
        if self.timing != "physical":
            st = proc.advance(u_k, self.T)
        else:
            d = delay_ns / 1e9
            st = proc.advance(self.u_held, d)
            if st == FLOW_OK:
                st = proc.advance(u_k, self.T - d)
            self.u_held = u_k
        if dev is not None and st == FLOW_OK:
            w = dev.disturbance()
            if w is not None:  # x_k+1 = phi_T(x_k, u_k) + w_k
                cast(OdeProcess, proc).perturb(w)  # a plant of equations (a scenario refuses one for an FMU)
        return st


__all__ = ["corrupt_payload", "EncoderProtocol", "ControllerProtocol", "PlantProtocol", "OdeProcess", "Send", "Withhold",
           "Decision", "skip_sample", "RECEIVED", "DEADLINE", "INVALID", "SUPERSEDED", "REASONS"]
