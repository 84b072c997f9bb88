"""The per-sample simulator (``simulate_loop``): one trajectory, sample by sample, with *separate*
encoder and decoder ends (``methods.EncoderEnd``, ``DecoderEnd``) that only see symbols and acks
(what a live run does), run through the protocol objects of ``testbed.loop.protocol`` that the live
nodes run too.  Returns every per-sample quantity (``SimResult``).  ``testbed.simulate`` holds the
batch kernel and the scenario level.

At every sample:  x_k -> encoder symbol (Algorithm 1) -> attacker (theta_k) ->
decoder q_k, u_k = (1 - theta_k) K q_k (Algorithm 2, law (2)) -> ack theta_k ->
both ends apply (xi), (E) -> plant x_{k+1} = phi_T(x_k, u_k).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from attackers.greedy import greedy_init, greedy_step
from plants.base import PlantFault

from ..loop.channel import ATTACKER, LATE, NetworkModel, SampleChannel, loss_cause, sample_channel
from ..loop.flow import DEFAULT_FLOW, FLOW_OK, FlowOptions
from ..loop.protocol import (
    DEADLINE,
    INVALID,
    RECEIVED,
    ControllerProtocol,
    EncoderProtocol,
    MethodFault,
    OdeProcess,
    PlantProtocol,
    Send,
    corrupt_payload,
)
from ..loop.quantizer import (
    QuantizerParams,
    control_input,
)
from ..methods.base import DecoderEnd, EncoderEnd, End, Method, symbol_code
from ..methods.bundled import PaperMethod

if TYPE_CHECKING:
    from attackers.schedule import Schedule
    from plants.base import Plant, PlantProcess

    from ..loop.device import DeviceSpec


SCORE_STATE = 0  # greedy attacker hurts where ||x_k||_inf is largest
SCORE_E = 1      # ... or where E_k is largest
SCORES = {"state": SCORE_STATE, "E": SCORE_E}


# ============================================================================ per-sample loop
def equal_where(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> bool:
    """``np.array_equal(a[mask], b[mask])`` (NaN differs from NaN), without copying the selected rows out:
    ``mask`` selects along the first axis.  A copy of the rows of a recording's column view was 16 ms of 600,000
    samples; this reads each column once."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or np.shape(mask) != a.shape[:1]:
        return bool(np.array_equal(a[mask], b[mask]))
    diff = a != b
    if diff.ndim > 1:
        diff = diff.any(axis=tuple(range(1, diff.ndim)))
    return not bool(np.any(diff & mask))


@dataclass
class SimResult:
    """Per-sample record of one closed-loop run (arrays indexed by k = 0..N-1)."""

    T: float
    t: np.ndarray
    x: np.ndarray          # x_k, (N, n)
    u: np.ndarray          # u_k as the controller sent it, (N, m)
    q: np.ndarray          # q_k at the decoder (0 when lost), (N, n)
    q_enc: np.ndarray      # q_k at the encoder (centre of the box of x_k), (N, n)
    xi_enc: np.ndarray     # xi_k at the encoder, (N, n) (NaN where the symbol was withheld)
    E_enc: np.ndarray      # E_k at the encoder, (N,) (NaN where withheld)
    xi_dec: np.ndarray
    E_dec: np.ndarray
    theta: np.ndarray      # theta_k (1: packet lost), (N,) uint8
    symbols: np.ndarray    # symbol sent by the encoder, (N,) int64 (-1: withheld)
    saturated: np.ndarray  # x_k outside Q(xi_k, E_k) at the encoder, (N,) bool
    x_final: np.ndarray    # x_N
    flow_status: int = FLOW_OK   # first non-ok flow status of the plant, if any
    diverged_at: int = -1        # sample at which the plant flow diverged, or -1
    K: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    reason: np.ndarray | None = None     # the controller's reason per sample (protocol.REASONS)
    withheld: np.ndarray | None = None   # the encoder withheld the symbol (a lost ack), (N,) bool
    loss_cause: np.ndarray | None = None  # why theta_k = 1: channel.ATTACKER, CHANNEL, LATE, WITHHELD (0: received)
    delays: np.ndarray | None = None     # physical timing: delta_k [ns] (None: ideal timing)
    u_missing: np.ndarray | None = None  # u_k never reached the plant (u = 0 after the deadline)
    counters: dict = field(default_factory=dict)
    plant_fault: str | None = None  # the true plant failed (``plants.PlantFault``): its one line
    plant_fault_at: int = -1        # ... at this sample (its advance over [t_k, t_k+1), or reset: 0)
    loop_state: np.ndarray | None = None  # both ends' xi, E, u_{k-1} after the last sample (``loop_state_of``)
    method_fault: str | None = None  # the method's end raised (its one line) ...
    method_fault_at: int = -1        # ... at this sample (the record holds samples 0..k-1; x_final = x_k)
    method_fault_role: str | None = None  # the node whose end raised: "encoder" or "controller"
    lockstep_breaks: list = field(default_factory=list)  # samples where the ends' shared state differed
    ends: tuple | None = None        # the encoder and decoder ends after the run (a method's continuation)
    x_meas: np.ndarray | None = None  # x_meas,k, what the sensor read ([plant.sensor]; None: x_k itself), (N, n)
    u_plant: np.ndarray | None = None  # the input that acted after the actuator ([plant.actuator]; None: u), (N, m)
    simulator: str | None = "per-sample"  # which simulator ran: "per-sample" (this loop), "batch" (``testbed.sim.trajectory``);
    #                                       a recording's: as its metadata says (None: a live run)

    @property
    def saturations(self) -> int:
        return int(self.saturated.sum())

    @property
    def final_norm(self) -> float:
        return float(np.max(np.abs(self.x_final)))

    @property
    def agree(self) -> bool:
        """Encoder and decoder xi_k, E_k identical at every sample the encoder sent (bit for bit)."""
        if self.lockstep_breaks:
            return False
        known = np.isfinite(self.E_enc)
        if self.withheld is None and not known.all():
            return False
        return equal_where(self.xi_enc, self.xi_dec, known) and equal_where(self.E_enc, self.E_dec, known)

    def intervals(self) -> Schedule:
        """The realized DoS schedule as (start, length) pairs: the runs of samples the attacker dropped
        (``loss_cause``; a loss of another cause, a ``[network]`` link's, a late or withheld sample, is not an
        attack; without ``loss_cause``, every lost sample)."""
        from attackers.schedule import Schedule

        th = self.theta if self.loss_cause is None else (np.asarray(self.loss_cause) == ATTACKER).astype(np.int64)
        return Schedule.from_theta(th, self.T)


class OnlineAttacker:
    """theta_k from a precomputed 0/1 sequence or from the greedy policy (online)."""

    def __init__(self, theta: npt.ArrayLike | None = None, greedy_params: npt.ArrayLike | None = None,
                 score: str = "state", T: float = 0.1):
        self.theta = None if theta is None else np.asarray(theta, dtype=np.uint8)
        self.greedy_params = None if greedy_params is None else np.asarray(greedy_params, dtype=np.float64)
        self.score = SCORES[score]
        self.T = T
        self._gstate = greedy_init()

    def decide(self, k: int, x_k: np.ndarray, E_k: float) -> int:
        if self.greedy_params is not None:
            s = float(np.max(np.abs(x_k))) if self.score == SCORE_STATE else float(E_k)
            return int(greedy_step(self._gstate, k, self.T, s, self.greedy_params))
        if self.theta is None or k >= len(self.theta):
            return 0
        return int(self.theta[k])


@dataclass(frozen=True)
class LinkEffects:
    """What the links between the nodes of a simulated run do, beyond the attacker's drops (the scenario's
    ``[network]`` model is one part of it: ``channel``, a ``testbed.loop.channel.NetworkModel``).

    ack_via_attacker : the ack of sample k crosses the attacker too, and is dropped iff
        the attacker dropped sample k (``testbed run --ack-via-attacker``).
    corrupt : {k: "range" | "length"}: the attacker replaces the payload of sample k by an
        out-of-range code or a payload of the wrong length (``testbed run --corrupt``).
    channel : the emulated channels (the scenario's ``[network]``, ``testbed.loop.channel``): per
        sample, the sensor link can lose x_k (the encoder never gets it), the symbol link the
        symbol (after the attacker), the ack link the ack (the encoder withholds), the actuation
        link u_k (u_missing); under physical timing a symbol later than the loss deadline is lost
        and the delays add to u_k's latency (``channel.sample_channel``).
    """

    ack_via_attacker: bool = False
    corrupt: tuple[tuple[int, str], ...] = ()
    channel: NetworkModel | None = None

    def samples(self, N: int, tpar: np.ndarray, n: int, m: int, symbol_bytes: int) -> SampleChannel | None:
        """The channel's effect on samples 0..N-1 (None without a channel)."""
        if self.channel is None:
            return None
        return sample_channel(self.channel, N, physical=bool(tpar[0]), loss_ns=int(tpar[4]), n=n, m=m,
                              symbol_bytes=symbol_bytes)


@dataclass(frozen=True)
class Replay:
    """What a recording says happened (``testbed resimulate``), one entry per sample.

    reason : the controller's decision reason (protocol.RECEIVED, DEADLINE, INVALID,
        SUPERSEDED; -1 where no controller record exists: treated as a loss)
    sensed : the encoder received x_k (False: the sensor message never reached it)
    withheld : the encoder withheld sample k (its ack for an earlier sample was late)
    u_missing : u_k never reached the plant: u_{k-1} held until the deadline, then 0
    delays : physical timing: delta_k [ns] as the plant measured it (None: ideal timing)
    """

    reason: np.ndarray
    sensed: np.ndarray
    withheld: np.ndarray
    u_missing: np.ndarray
    delays: np.ndarray | None = None


def simulate_loop(plant: Plant | None, K: npt.ArrayLike, qp: QuantizerParams, x0: npt.ArrayLike, n_steps: int,
                  attacker: OnlineAttacker | None, flow: FlowOptions = DEFAULT_FLOW, *, model: Plant | None = None,
                  process: PlantProcess | None = None, timing: npt.ArrayLike | None = None,
                  latency: npt.ArrayLike | None = None, u_max: float = math.inf, effects: LinkEffects | None = None,
                  replay: Replay | None = None, method: Method | None = None, device: DeviceSpec | None = None,
                  states: np.ndarray | None = None, measured: np.ndarray | None = None) -> SimResult:
    """One trajectory, sample by sample, through the protocol state machines of the live nodes.

    The encoder (``protocol.EncoderProtocol``), the controller (``ControllerProtocol``)
    and the plant (``PlantProtocol``) are the objects the live nodes run; here a
    simulated network connects them.  Per sample k: the plant samples x_k; the
    encoder sends a symbol or withholds it (a lost ack); the attacker drops or
    forwards it (or corrupts it); the controller decides u_k, theta_k and acks; the
    plant holds u_{k-1} for delta_k (physical timing) and then applies u_k.

    ``plant`` is the true plant (an ODE plant; or give ``process``, any true-plant
    process such as an FMU), ``model`` the plant model of the encoder's and decoder's
    predictions (default: ``plant``).  ``timing``: ``Scenario.timing_params`` ([physical,
    scheduled, delta_s, d T, loss deadline] in ns; None: ideal timing) and ``latency``
    (ns, a scalar or (N,)): when u_k reaches the plant after t_k (a lost sample's after the
    loss deadline).  ``replay``: re-run what a recording says happened (the attacker is
    then ignored: theta_k follows the recorded decisions; delta_k is the recorded one).

    A true-plant process that raises ``plants.PlantFault`` (an FMU step that failed) ends
    the run at that sample: the result holds samples 0..k, x_final is the process's state
    at the fault, and ``plant_fault`` / ``plant_fault_at`` say what and where (a failed
    ``reset`` gives a run of no samples).  Nothing is raised.

    ``method``: the coding-and-control method (``testbed.methods.Method``; default the paper's).
    A method whose ends raise ends the run at that sample (``method_fault``, ``method_fault_at``);
    one whose ends' shared state differs is counted in ``lockstep_breaks`` (``agree`` is then False).

    ``device``: the plant's sensor, actuator and disturbance (``testbed.loop.device.DeviceSpec``, the
    scenario's ``sc.plant.device``): the encoder and the attacker see x_meas,k, the true plant
    integrates the input the actuator lets through, and x_k+1 carries the disturbance.

    ``states``, ``measured``: the loop on a recorded plant (``testbed.runs.replay``): x_k is ``states[k]``
    (what the plant reported, not the process's state) and the encoder reads ``measured[k]`` (x_meas,k;
    None: x_k, or the sensor model of ``device``).
    """
    model = plant if model is None else model
    if model is None:
        raise ValueError("simulate_loop needs the plant or its model")
    n, m = model.n, model.m
    K = np.asarray(K, dtype=np.float64).reshape(m, n)
    N = int(n_steps)
    net = effects or LinkEffects()
    corrupt = dict(net.corrupt)
    if process is None:
        if plant is None:
            raise ValueError("simulate_loop needs the true plant or its process")
        process = OdeProcess(plant, flow)
    try:
        process.reset(np.asarray(x0, dtype=np.float64))
    except PlantFault as e:  # the true plant cannot start: a run of no samples, reported as data
        z = np.zeros((0, n))
        return SimResult(T=qp.T, t=np.zeros(0), x=z, u=np.zeros((0, m)), q=z, q_enc=z, xi_enc=z,
                         E_enc=np.zeros(0), xi_dec=z, E_dec=np.zeros(0), theta=np.zeros(0, dtype=np.uint8),
                         symbols=np.zeros(0, dtype=np.int64), saturated=np.zeros(0, dtype=bool),
                         x_final=np.asarray(x0, dtype=np.float64).copy(), K=K, plant_fault=str(e),
                         plant_fault_at=0)
    tpar = np.zeros(5, dtype=np.int64) if timing is None else np.asarray(timing, dtype=np.int64)
    physical = bool(tpar[0])
    if replay is not None and replay.delays is not None:
        physical = True
    pp = PlantProtocol(process, qp.T, timing="physical" if physical else "ideal",
                       actuation="scheduled" if tpar[1] else "arrival", sched_ns=int(tpar[2]),
                       deadline_ns=int(tpar[3]), loss_ns=int(tpar[4]), u_max=u_max,
                       device=None if device is None else device.make(n, m, qp.T))
    x_meas = np.full((N, n), np.nan) if device is not None and device.sensor is not None else None
    u_plant = np.zeros((N, m)) if device is not None and device.actuator is not None else None
    lat = np.broadcast_to(np.asarray(0 if latency is None else latency, dtype=np.int64), (N,))
    delays = np.zeros(N, dtype=np.int64) if physical else None
    own = method is not None   # a method of the caller's: a raise is its fault, not the testbed's
    if method is None:
        method = PaperMethod()
    encp = EncoderProtocol(method.make_encoder(model, K, qp, flow), N)
    ctlp = ControllerProtocol(method.make_decoder(model, K, qp, flow), N)
    chan = net.samples(N, tpar, n, m, ctlp.codebook.nbytes) if replay is None else None
    dropped = np.zeros(N, dtype=bool)   # the attacker dropped or corrupted sample k's symbol
    enc_state: dict = {}
    breaks = []
    mfault, mfault_at, mfault_role = None, -1, None
    cb = ctlp.codebook
    rec = {k: np.full((N, n), np.nan) for k in ("x", "q", "q_enc", "xi_enc", "xi_dec")}
    u_rec = np.zeros((N, m))
    E_enc = np.full(N, np.nan)
    E_dec = np.full(N, np.nan)
    theta = np.ones(N, dtype=np.uint8)
    symbols = np.full(N, -1, dtype=np.int64)
    sat = np.zeros(N, dtype=bool)
    reason = np.full(N, -1, dtype=np.int64)
    withheld = np.zeros(N, dtype=bool)
    u_missing = np.zeros(N, dtype=bool)
    acks: list = []          # acks on their way to the encoder (delivered before the next sensor sample)
    status, diverged_at = FLOW_OK, -1
    fault, fault_at = None, -1
    last = N

    def record(d) -> None:
        if d.state is not None and d.k in enc_state and not np.array_equal(enc_state.pop(d.k), d.state,
                                                                           equal_nan=True):
            breaks.append(d.k)
        theta[d.k] = d.theta
        rec["q"][d.k] = d.q
        rec["xi_dec"][d.k] = d.xi
        E_dec[d.k] = d.E
        u_rec[d.k] = d.u
        reason[d.k] = d.reason

    for k in range(N):
        x = process.x if states is None else np.array(states[k], dtype=np.float64)
        rec["x"][k] = x
        if measured is not None:
            x = np.array(measured[k], dtype=np.float64)
            if x_meas is not None:
                x_meas[k] = x
        elif x_meas is not None:
            x = x_meas[k] = pp.measure(k, x)
        try:
            send, decs = _method_sample(encp, ctlp, replay, acks, k, x, attacker, corrupt, cb, chan)
        except Exception as e:  # a method's end raised: the run ends at this sample
            if not own:
                raise
            mf = MethodFault(method.display_name(), k, e, _raising_role(e, encp.enc))
            mfault, mfault_at, mfault_role, last = mf.line, k, mf.role, k
            break
        if isinstance(send, Send):
            if send.state is not None:
                enc_state[k] = send.state
            symbols[k], sat[k] = symbol_code(send.symbol), send.saturated
            rec["xi_enc"][k] = send.xi
            E_enc[k] = send.E
            rec["q_enc"][k] = send.q
        else:  # withheld (a lost ack), or x_k never came (the sensor link lost it: not the encoder's doing)
            withheld[k] = chan is None or bool(chan.sensed[k])
        drop = decs.pop()
        dropped[k] = bool(drop) or k in corrupt
        for d in decs:
            record(d)
            if not (net.ack_via_attacker and drop) and not (chan is not None and chan.ack_lost[d.k]):
                acks.append((d.k, d.theta, d.last_rx))
        d = decs[-1]
        # --- plant
        u_k, _fault = pp.check_input(d.u)
        dns = 0
        if replay is not None:
            if replay.u_missing[k]:
                u_k = None
            if physical:
                assert replay.delays is not None  # physical timing: the replay carries the recorded delays
                dns = int(replay.delays[k])
        else:
            if chan is not None and chan.actuation_lost[k]:
                u_k = None
            if physical:
                arr = int(lat[k]) + (pp.loss_ns if d.theta == 1 else 0)
                if chan is not None:
                    arr += int(chan.actuation_ns[k]) + (0 if d.theta == 1 else int(chan.upstream_ns[k]))
                if u_k is None or arr > pp.deadline_ns:  # u_{k-1} held until the deadline, then 0
                    u_k, dns = None, pp.deadline_ns
                else:
                    dns = pp.delay_ns(arr, d.theta)
        if u_k is None:
            u_missing[k] = True
        if delays is not None:  # physical timing
            delays[k] = dns
        try:
            st = pp.step(u_k, dns)
        except PlantFault as e:  # the run stops at this sample (x_final = x_k): reported, not raised
            fault, fault_at, last = str(e), k, k + 1
            break
        if u_plant is not None:
            u_plant[k] = pp.u_applied
        if st != FLOW_OK:
            status, diverged_at, last = int(st), k, k + 1
            break
    if mfault is None:
        for a in acks:
            encp.ack(*a)
    sl = slice(0, last)
    cause = None   # a replay's causes are the recording's (``testbed report``)
    if replay is None:
        c = {} if chan is None else {"sensed": chan.sensed[sl], "symbol_lost": chan.symbol_lost[sl], "late": chan.late[sl]}
        cause = loss_cause(theta[sl], withheld=withheld[sl], attacker=dropped[sl], **c)
    ctl_counters = ctlp.counters()
    if cause is not None:  # a late symbol arrives after its sample was decided (counted as the live controller does)
        ctl_counters["late"] += int(np.count_nonzero(cause == LATE))
    return SimResult(T=qp.T, t=np.arange(last) * qp.T, x=rec["x"][sl], u=u_rec[sl], q=rec["q"][sl],
                     q_enc=rec["q_enc"][sl], xi_enc=rec["xi_enc"][sl], E_enc=E_enc[sl],
                     xi_dec=rec["xi_dec"][sl], E_dec=E_dec[sl], theta=theta[sl], symbols=symbols[sl],
                     saturated=sat[sl], x_final=process.x, flow_status=status, diverged_at=diverged_at, K=K,
                     reason=reason[sl], withheld=withheld[sl], u_missing=u_missing[sl], loss_cause=cause,
                     delays=None if delays is None else delays[:last].copy(),
                     counters={"encoder": encp.counters(), "controller": ctl_counters,
                               "plant": {"rejected_nonfinite": pp.rejected_nonfinite, "clamped": pp.clamped,
                                         **({} if pp.device is None else pp.device.counters())}},
                     plant_fault=fault, plant_fault_at=fault_at,
                     loop_state=loop_state_of(encp.enc, ctlp.dec) if mfault is None else None,
                     method_fault=mfault, method_fault_at=mfault_at, method_fault_role=mfault_role,
                     lockstep_breaks=breaks,
                     ends=(encp.enc, ctlp.dec), x_meas=None if x_meas is None else x_meas[sl],
                     u_plant=None if u_plant is None else u_plant[sl])


def _raising_role(e: BaseException, enc) -> str:
    """Which end raised ``e``: "encoder" when a frame of its traceback runs a method of ``enc``, else
    "controller" (the decoder end, where the live run's controller node runs it)."""
    tb = e.__traceback__
    while tb is not None:
        if tb.tb_frame.f_locals.get("self") is enc:
            return "encoder"
        tb = tb.tb_next
    return "controller"


def _method_sample(encp, ctlp, replay, acks, k, x, attacker, corrupt, cb, chan=None):
    """One sample of the method's ends through the protocol: the encoder (acks first), the
    attacker, the channel (``chan``: sensor and symbol links) and the controller.  Returns
    (send, decisions + [drop])."""
    if replay is None or not replay.withheld[k]:
        for a in acks:
            encp.ack(*a)
        acks.clear()
    send = None
    if (replay.sensed[k] if replay is not None else (chan is None or chan.sensed[k])):
        send = encp.sensor(k, x)
    payload = cb.pack(send.symbol) if isinstance(send, Send) else None
    if replay is None:
        drop = attacker.decide(k, x, encp.enc.E) if attacker is not None else 0
        if drop:
            payload = None
        elif payload is not None and k in corrupt:
            payload = corrupt_payload(cb, payload, corrupt[k])
        if chan is not None and (chan.symbol_lost[k] or chan.late[k]):
            payload = None
    else:
        drop = 0
        r = int(replay.reason[k])
        if r == INVALID and payload is not None:
            payload = corrupt_payload(cb, payload, "length")
        elif r != RECEIVED:
            payload = None
    decs = ctlp.symbol(k, payload) if payload is not None else [ctlp.deadline(k)]
    return send, decs + [drop]


def loop_state_of(enc: End, dec: End) -> np.ndarray:
    """The packed loop state (``loop_state_width``) of an encoder and a decoder end (``methods.End``)."""
    return np.concatenate([enc.xi, [enc.E], enc.u_prev, dec.xi, [dec.E], dec.u_prev]).astype(np.float64)


def loop_state_from_samples(res: SimResult, model: Plant, qp: QuantizerParams,
                            flow: FlowOptions = DEFAULT_FLOW) -> np.ndarray | None:
    """Both ends' state after the last sample of a run whose per-sample record is all there is
    (a recording): the controller's xi, E of its last sample (the encoder's if the controller's
    is missing), updated once by rules (xi), (E) with that sample's symbol and theta (u_{k-1}
    from the sample before), used for both ends.  None when neither end's state is known."""
    N = len(res.theta)
    if N == 0:
        return None
    if np.isfinite(res.E_dec[-1]):
        xi, E = res.xi_dec[-1], res.E_dec[-1]
    elif np.isfinite(res.E_enc[-1]):  # no controller record of the last sample: the encoder's (the same
        xi, E = res.xi_enc[-1], res.E_enc[-1]  # in lockstep)
    else:
        return None
    dec = PaperMethod().make_decoder(model, res.K, qp, flow)
    cb = dec.codebook
    dec.xi = np.array(xi, dtype=np.float64)
    dec.E = float(E)
    if (N >= 2 and int(res.theta[-2]) == 0 and int(res.symbols[-2]) != cb.overflow
            and np.all(np.isfinite(res.q[-2]))):
        up = np.empty(model.m)
        q_prev = np.ascontiguousarray(res.q[-2], dtype=np.float64)  # a row of a recording's column-major q is
        control_input(dec.K, q_prev, 0, False, up)                  # strided: one kernel signature, not two
        dec.u_prev = up
    th = int(res.theta[-1])
    sym = int(res.symbols[-1])
    dec.step(None if th == 1 or sym < 0 else sym)
    return loop_state_of(dec, dec)


def record_replay(res: SimResult) -> Replay:
    """What a run's per-sample record says happened, as a :class:`Replay` of its ends: the controller's
    reason (``res.reason``; without one, theta_k: received or lost), the samples the encoder withheld
    (``res.withheld``), the ones it never saw (no symbol and not withheld).  ``testbed report`` builds the
    same from a recording's columns (``testbed.record.summary.build_summary``)."""
    N = len(res.theta)
    theta = np.asarray(res.theta, dtype=np.int64)
    reason = np.where(theta == 0, RECEIVED, DEADLINE) if res.reason is None else np.asarray(res.reason, np.int64)
    withheld = np.zeros(N, dtype=bool) if res.withheld is None else np.asarray(res.withheld, dtype=bool)
    sensed = (np.asarray(res.symbols) >= 0) | withheld
    return Replay(reason=reason.astype(np.int64), sensed=sensed, withheld=withheld, u_missing=np.zeros(N, bool))


def ends_from_record(res: SimResult, method: Method, model: Plant, K: np.ndarray, qp: QuantizerParams,
                     flow: FlowOptions = DEFAULT_FLOW, replay: Replay | None = None) -> tuple[EncoderEnd, DecoderEnd]:
    """Both ends of ``method`` after the last sample of a run, rebuilt from its per-sample record alone.

    The method's encoder and decoder ends run through the protocol objects (``_method_sample``, as
    ``simulate_loop`` and the live nodes run them) fed with what the record says: x_k (x_meas,k where a
    sensor read it) at the encoder, the controller's decisions and the withheld samples (``replay``,
    default :func:`record_replay`); no plant is integrated.  A simulated run and its recording give the
    same record, hence the same ends: the escape verdict (``testbed.sim.batch.escaped_run``) continues
    the loop from these.  Returns (encoder, decoder), or raises what the method's ends raise.
    """
    replay = record_replay(res) if replay is None else replay
    ends = RecordEnds(method, model, K, qp, flow, len(res.theta))
    ends.feed(0, np.asarray(res.x if res.x_meas is None else res.x_meas, dtype=np.float64), replay)
    return ends.ends()


class _From:
    """A chunk's per-sample array indexed by the run's sample k (the chunk starts at sample ``k0``)."""

    def __init__(self, a, k0: int):
        self.a, self.k0 = a, k0

    def __getitem__(self, k: int) -> Any:
        return self.a[k - self.k0]


def _from(a: np.ndarray, k0: int) -> Any:
    """:class:`_From`, read by the protocol objects as the array it stands for."""
    return _From(a, k0)


class RecordEnds:
    """:func:`ends_from_record` fed a chunk of the record at a time (``feed``, in the order of the samples):
    the same ends, with the protocol objects and the pending acks carried from chunk to chunk."""

    def __init__(self, method: Method, model: Plant, K: npt.ArrayLike, qp: QuantizerParams, flow: FlowOptions,
                 n_steps: int) -> None:
        K = np.asarray(K, dtype=np.float64).reshape(model.m, model.n)
        self.encp = EncoderProtocol(method.make_encoder(model, K, qp, flow), n_steps)
        self.ctlp = ControllerProtocol(method.make_decoder(model, K, qp, flow), n_steps)
        self.acks: list = []

    def feed(self, k0: int, X: npt.ArrayLike, replay: Replay) -> None:
        """Samples k0 .. k0 + len(X) - 1: x_k (x_meas,k where a sensor read it) and the chunk's ``Replay``."""
        rp = Replay(reason=_from(replay.reason, k0), sensed=_from(replay.sensed, k0),
                    withheld=_from(replay.withheld, k0), u_missing=_from(replay.u_missing, k0))
        X = np.asarray(X, dtype=np.float64)
        encp, ctlp, acks = self.encp, self.ctlp, self.acks
        for i in range(len(X)):
            _send, decs = _method_sample(encp, ctlp, rp, acks, k0 + i, X[i], None, {}, ctlp.codebook)
            decs.pop()
            acks.extend((d.k, d.theta, d.last_rx) for d in decs if d is not None)

    def ends(self) -> tuple[EncoderEnd, DecoderEnd]:
        """(encoder, decoder) after the samples fed."""
        for a in self.acks:
            self.encp.ack(*a)
        self.acks = []
        return self.encp.enc, self.ctlp.dec


class StopCriterion(Protocol):
    """What :func:`continue_ends` reads of its criterion (``testbed.sim.batch.EscapeCriterion``)."""

    @property
    def x_tol(self) -> float: ...
    @property
    def E_tol(self) -> float: ...
    @property
    def x_out(self) -> float: ...
    def steps(self, T: float) -> int: ...


def continue_ends(plant: Plant, x_final: npt.ArrayLike, ends: tuple[EncoderEnd, DecoderEnd], c: StopCriterion,
                  T: float, flow: FlowOptions, u_max: float) -> bool:
    """The escape criterion ``c`` (``testbed.sim.batch.EscapeCriterion``) for a method without a batch
    kernel: its own two ends (``ends``, :func:`ends_from_record`),
    continued from where the run ended (``x_final``) with theta_k = 0 and the true plant under ideal timing.
    Escaped unless ||x|| < x_tol with both ends' E below E_tol within the horizon."""
    enc, dec = ends
    proc = OdeProcess(plant, flow)
    proc.reset(np.asarray(x_final, dtype=np.float64))
    for _ in range(c.steps(T)):
        x = proc.x
        nrm = float(np.max(np.abs(x)))
        if nrm < c.x_tol and float(getattr(enc, "E", 0.0)) < c.E_tol and float(getattr(dec, "E", 0.0)) < c.E_tol:
            return False
        if nrm > c.x_out:
            return True
        try:
            sym, _sat = enc.encode(x)
            u, _q, _th = dec.decide(sym)
            dec.commit()
            enc.ack(0)
        except Exception:  # noqa: BLE001 - the method failed: the loop did not recover
            return True
        u = np.clip(np.asarray(u, dtype=np.float64), -u_max, u_max)
        if not np.all(np.isfinite(u)) or proc.advance(u, T) != FLOW_OK:
            return True
    return True
