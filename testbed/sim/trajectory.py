"""``simulate_scenario``: a scenario on the batch kernel where it can run, else on the per-sample loop.

The per-sample loop (``testbed.sim.loop.simulate_loop``) runs the live nodes' protocol objects
one sample at a time in Python (about 5,000 samples/s).  For the runs the batch kernel covers
it is replaced here by the batch kernel itself (``sim.kernel._batch_kernel``) over one trajectory, keeping every per-sample
array of a ``SimResult`` (x_k, u_k, q_k at both ends, xi_k and E_k at both ends, theta_k, the
symbols, saturations, delays, ...): the same numbers bit for bit (``tests/sim/test_simbatch.py``
compares every array and the JSON summary), hundreds of times faster.

The kernel runs a scenario when (:func:`kernel_refusal` says why not otherwise):

* the true plant and the model are bundled plants (``plants/``; not an FMU, not a user's class);
* the method is a bundled one with a kernel mode (``paper`` in both quantizer modes, ``zoom``,
  ``static``, ``unquantized``, ``unquantized-hold``; a user's method has none);
* the links are plain: no ``--ack-via-attacker``, no ``--corrupt`` (with those an ack
  can be lost and the encoder withholds samples, which only the protocol objects model);
* ideal or physical timing, an offline schedule or the online greedy attacker (all it has);
* a ``[network]`` channel (``testbed.loop.channel``): its draws are made ahead and given to the kernel per sample
  (the controller cannot receive it; the upstream delay; u_k lost), and the samples the encoder withholds
  after a lost ack are computed ahead (``channel.withheld_pattern``); only the greedy attacker scoring E
  with a lossy ack link (it reads the withholding encoder's E_k) runs the loop.

Everything else runs the per-sample loop.  ``simulator="per-sample"`` forces the loop
(``testbed simulate --simulator per-sample``); a ``SimResult`` says which ran (``simulator``).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, cast

import numpy as np
import numpy.typing as npt

from attackers.greedy import greedy_init

from ..loop.channel import LATE, loss_cause
from ..loop.flow import FLOW_OK
from .kernel import COUNTS, TRACE_INTS, _batch_kernel, loop_state_width, trace_width
from .loop import SCORES, LinkEffects, OnlineAttacker, SimResult, simulate_loop

if TYPE_CHECKING:
    from plants.base import Plant

    from ..loop.channel import SampleChannel
    from ..methods.base import EncoderEnd
    from ..scenario.spec import Scenario

#: ``simulate_scenario(simulator=...)``: "auto" (the kernel where it can run), "batch" (the kernel or an
#: error), "per-sample" (the loop always)
SIMULATORS = ("auto", "batch", "per-sample")
BATCH = "batch"
PER_SAMPLE = "per-sample"


def _bundled(plant: Plant) -> bool:
    return type(plant).__module__.split(".")[0] == "plants" and hasattr(type(plant).rhs, "cfunc")


def kernel_refusal(sc: Scenario, effects: LinkEffects | None = None) -> str | None:
    """Why the batch kernel cannot run scenario ``sc`` (one phrase), or None when it can."""
    if sc.plant.fmu is not None:
        return "the true plant is an FMU"
    if sc.plant.device is not None:
        return f"the plant is a device ({sc.plant.device.describe()}: the protocol objects model it)"
    try:
        if not _bundled(sc.make_plant()) or not _bundled(sc.make_model()):
            return "the plant or the model is not a bundled plant"
    except Exception as e:  # noqa: BLE001 - whatever makes the plant fail, the per-sample loop reports it
        return f"the plant cannot be made here ({type(e).__name__})"
    method = sc.make_method()
    if method.kernel_code(sc.quantizer) is None:
        return f"method {method.display_name()!r} has no batch kernel (a user's method)"
    if effects is not None and (effects.ack_via_attacker or effects.corrupt):
        return "acks via the attacker or corrupted payloads (only the protocol objects model them)"
    if sc.attack.online and sc.attack.kind != "greedy":
        return f"the online attacker {sc.attack.kind!r}"
    if effects is not None and effects.channel is not None and effects.channel != sc.network:
        return "a channel other than the scenario's [network] (the kernel applies the scenario's)"
    if sc.network is not None and sc.attack.online and sc.attack.score == "E" and sc.network.link("ack").loss > 0:
        return "the greedy attacker scoring E with a lossy ack link (it reads the encoder's E while it withholds)"
    return None


class _Ledger:
    """An encoder end that only keeps the books: ``EncoderProtocol``'s counters of a kernel run with a
    channel come from the protocol object itself, fed the samples' fates (the numbers are the kernel's)."""

    xi = E = q = None
    saturations = 0

    def encode(self, x: np.ndarray) -> tuple[int, bool]:
        return 0, False

    def ack(self, theta: int) -> None:
        pass


def _encoder_counters(chan: SampleChannel, theta: np.ndarray, sat: np.ndarray, last: int) -> dict:
    """The encoder's counters (``EncoderProtocol.counters``) of a kernel run with a channel: the same
    protocol object driven as ``loop.simulate_loop`` drives it (acks before the next sensor sample)."""
    from ..loop.protocol import EncoderProtocol

    encp = EncoderProtocol(cast("EncoderEnd", _Ledger()), len(chan.sensed))  # a stand-in: the members it reads
    acks: list = []
    last_rx = -1
    for k in range(last):
        for a in acks:
            encp.ack(*a)
        acks.clear()
        if chan.sensed[k]:
            encp.sensor(k, ())  # the ledger encodes nothing: no state
        if theta[k] == 0:
            last_rx = k
        if not chan.ack_lost[k]:
            acks.append((k, int(theta[k]), last_rx))
    for a in acks:
        encp.ack(*a)
    out = encp.counters()
    out["saturations"] = int(sat.sum())
    return out


def simulate_kernel(sc: Scenario, N: int, latency: npt.ArrayLike | None = None,
                    theta: npt.ArrayLike | None = None) -> SimResult:
    """Scenario ``sc`` for N samples on the batch kernel with its full trace (``kernel_refusal(sc)`` must be None).

    ``theta``: theta_k for k = 0..N-1 decided elsewhere (a recording's, ``testbed.runs.resimulate``): the
    attacker and the ``[network]`` channel are left out, every sample is sensed and sent."""
    plant, model = sc.make_plant(), sc.make_model()
    n, m = model.n, model.m
    qp = sc.quantizer
    method = sc.make_method()
    code = method.kernel_code(qp)
    if code is None:  # kernel_refusal(sc) says so first
        raise ValueError(f"method {method.display_name()!r} has no batch kernel")
    mode = int(code)
    E0 = float(method.kernel_E0(qp))
    dpar = np.zeros(4) if mode == 4 else np.ascontiguousarray(qp.dpar, dtype=np.float64)
    K = np.ascontiguousarray(np.asarray(sc.K, dtype=np.float64).reshape(m, n))
    if theta is not None:
        gp = np.zeros((0, 5))
        tab = np.ascontiguousarray(theta, dtype=np.uint8).reshape(1, -1)
    elif sc.attack.online:
        gp = np.ascontiguousarray(sc.attack.greedy_params(), dtype=np.float64).reshape(1, 5)
        tab = np.zeros((1, 0), dtype=np.uint8)
    else:
        gp = np.zeros((0, 5))
        th = sc.theta(N)
        tab = np.zeros((1, 0), dtype=np.uint8) if th is None else np.ascontiguousarray(th, dtype=np.uint8).reshape(1, -1)
    tpar = np.ascontiguousarray(sc.timing_params, dtype=np.int64)
    physical = bool(tpar[0])
    if latency is None:
        latency = sc.sim_latency(N)
    lat = np.broadcast_to(np.asarray(0 if latency is None else latency, dtype=np.int64), (N,))
    cb = method.codebook(n, qp)
    chan = None if theta is not None else LinkEffects(channel=sc.network).samples(N, tpar, n, m, cb.nbytes)
    ctab = np.zeros((4, N), dtype=np.int64)
    if chan is not None:
        ctab[0] = chan.forced
        ctab[1] = chan.upstream_ns
        ctab[2] = chan.actuation_lost
        lat = lat + chan.actuation_ns
    lat = np.ascontiguousarray(lat.reshape(1, N))
    one = np.zeros(1, dtype=np.int64)
    X_rec, E_rec, TH = np.zeros((1, N, n)), np.zeros((1, N)), np.zeros((1, N), dtype=np.uint8)
    tf = np.zeros((1, N, trace_width(n, m)))
    ti = np.zeros((1, N, TRACE_INTS), dtype=np.int64)
    x_final = np.zeros((1, n))
    state_final = np.zeros((1, loop_state_width(n, m)))
    status, stop_k = np.zeros(1, np.int8), np.zeros(1, np.int64)
    counts = np.zeros((1, COUNTS), dtype=np.int64)
    _batch_kernel(type(plant).rhs.cfunc, plant.p, type(model).rhs.cfunc, model.p, float(qp.T), sc.flow.as_array(),
                  K, np.ascontiguousarray(sc.x0, dtype=np.float64).reshape(1, n), E0, int(qp.M), float(qp.Lambda),
                  mode, float(qp.sigma), float(qp.E_min), dpar, float(sc.controller.u_max), tab, one, tpar, lat, one,
                  gp, greedy_init(), SCORES[sc.attack.score], N, True, X_rec, E_rec, TH, x_final, np.zeros(1),
                  status, stop_k, np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1), np.zeros(1, np.int64),
                  np.zeros((0, state_final.shape[1])), np.zeros(3), state_final, ctab, tf, ti, counts)
    x_final, state_final, tf, ti, EE, TH = x_final[0], state_final[0], tf[0], ti[0], E_rec[0], TH[0]
    col = np.ascontiguousarray
    a = {"x": X_rec[0], "q": col(tf[:, :n]), "q_enc": col(tf[:, n:2 * n]), "xi_enc": col(tf[:, 2 * n:3 * n]),
         "xi_dec": col(tf[:, 3 * n:4 * n])}
    U, ED = col(tf[:, 4 * n:4 * n + m]), col(tf[:, 4 * n + m])
    SYM, SAT, UMISS, DEL = col(ti[:, 0]), ti[:, 1].astype(bool), ti[:, 2].astype(bool), col(ti[:, 3])
    last, code = int(stop_k[0]), int(status[0])
    nrej, nclamp, novf = (int(v) for v in counts[0])
    sl = slice(0, last)
    theta_k = TH[sl].copy()
    lost = int(theta_k.sum())
    sat = SAT[sl].copy()
    enc_counters = {"sent": last, "withheld": 0, "saturations": int(sat.sum()), "desync_episodes": 0,
                    "stale_sensor": 0, "stale_acks": 0, "inconsistent_acks": 0}
    withheld = np.zeros(last, dtype=bool)
    c = {}
    if chan is not None:  # what the encoder did not send: as the per-sample loop records it
        withheld = chan.withheld[sl].copy()
        unsent = withheld | ~chan.sensed[sl]
        SYM[sl][unsent] = -1
        sat[unsent] = False
        for arr in (a["xi_enc"], a["q_enc"]):
            arr[sl][unsent] = np.nan
        EE[sl][unsent] = np.nan
        enc_counters = _encoder_counters(chan, theta_k, sat, last)
        c = {"sensed": chan.sensed[sl], "symbol_lost": chan.symbol_lost[sl], "late": chan.late[sl]}
    cause = loss_cause(theta_k, withheld=withheld, attacker=ctab[3, sl] != 0, **c)
    counters = {"encoder": enc_counters,
                "controller": {"received": last - lost, "lost_deadline": lost, "invalid": 0,
                               "late": int(np.count_nonzero(cause == LATE)),
                               "superseded": 0, "future": 0, "overflows": novf, "decided": last},
                "plant": {"rejected_nonfinite": nrej, "clamped": nclamp}}
    return SimResult(T=qp.T, t=np.arange(last) * qp.T, x=a["x"][sl], u=U[sl], q=a["q"][sl], q_enc=a["q_enc"][sl],
                     xi_enc=a["xi_enc"][sl], E_enc=EE[sl], xi_dec=a["xi_dec"][sl], E_dec=ED[sl], theta=theta_k,
                     symbols=SYM[sl], saturated=sat, x_final=x_final,
                     flow_status=FLOW_OK if code == 0 else code, diverged_at=-1 if code == 0 else last - 1, K=K,
                     reason=theta_k.astype(np.int64), withheld=withheld, u_missing=UMISS[sl], loss_cause=cause,
                     delays=DEL[sl].copy() if physical else None, counters=counters, loop_state=state_final,
                     simulator=BATCH)


def simulate_scenario(sc: Scenario, *, n_steps: int | None = None, effects: LinkEffects | None = None,
                      latency: npt.ArrayLike | None = None, simulator: str = "auto") -> SimResult:
    """Run a scenario (see ``testbed.scenario``): on the batch kernel where it can run, else per sample.

    The true plant is ``[plant]`` (``sc.make_process()``), the predictions use ``[model]``;
    under physical timing the latency of u_k comes from ``[run] sim_delay`` unless
    ``latency`` (ns) is given.  ``simulator``: "auto" (the kernel when :func:`kernel_refusal`
    allows it, the per-sample loop otherwise), "batch" (the kernel, ``ValueError`` when it cannot
    run ``sc``), "per-sample" (the loop of the live nodes' protocol objects).  Both give the same
    numbers; ``SimResult.simulator`` says which ran.
    """
    if simulator not in SIMULATORS:
        raise ValueError(f"simulator must be one of {', '.join(SIMULATORS)}, got {simulator!r}")
    N = sc.n_steps if n_steps is None else int(n_steps)
    if sc.network is not None:  # [network]: the emulated channels, applied by both simulators
        effects = dataclasses.replace(effects or LinkEffects(), channel=sc.network)
    if simulator != PER_SAMPLE:
        why = kernel_refusal(sc, effects)
        if why is None:
            return simulate_kernel(sc, N, latency)
        if simulator == BATCH:
            raise ValueError(f"the batch kernel cannot run scenario {sc.name}: {why}")
    if sc.attack.online:
        att = OnlineAttacker(greedy_params=sc.attack.greedy_params(), score=sc.attack.score, T=sc.T)
    else:
        att = OnlineAttacker(theta=sc.theta(N), T=sc.T)
    if latency is None:
        latency = sc.sim_latency(N)
    process = sc.make_process()
    try:
        return simulate_loop(None, sc.K, sc.quantizer, sc.x0, N, att, sc.flow, model=sc.make_model(),
                             process=process, timing=sc.timing_params, latency=latency,
                             u_max=sc.controller.u_max, effects=effects, method=sc.make_method(),
                             device=sc.plant.device)
    finally:
        process.close()
