"""``simulate_scenario``: a scenario on the batch kernel where it can run, else on the per-sample loop.

The per-sample loop (``testbed.simloop.simulate_loop``) runs the live nodes' protocol objects
one sample at a time in Python (about 5,000 samples/s).  For the runs the batch kernel covers
it is replaced here by one compiled pass over the same arithmetic that keeps every per-sample
array of a ``SimResult`` (x_k, u_k, q_k at both ends, xi_k and E_k at both ends, theta_k, the
symbols, saturations, delays, ...): the same numbers bit for bit (``tests/test_simbatch.py``
compares every array and the JSON summary), hundreds of times faster.

The kernel runs a scenario when (:func:`kernel_refusal` says why not otherwise):

* the true plant and the model are bundled plants (``plants/``; not an FMU, not a user's class);
* the method is a bundled one with a kernel mode (``paper`` in both quantizer modes, ``zoom``,
  ``static``, ``unquantized``, ``unquantized-hold``; a user's method has none);
* the network is the plain one: no ``--ack-via-attacker``, no ``--corrupt`` (with those an ack
  can be lost and the encoder withholds samples, which only the protocol objects model);
* ideal or physical timing, an offline schedule or the online greedy attacker (all it has);
* a ``[network]`` channel (``testbed.channel``): its draws are made ahead and given to the kernel per sample
  (the controller cannot receive it; the upstream delay; u_k lost), and the samples the encoder withholds
  after a lost ack are computed ahead (``channel.withheld_pattern``); only the greedy attacker scoring E
  with a lossy ack link (it reads the withholding encoder's E_k) runs the loop.

Everything else runs the per-sample loop.  ``simulator="per-sample"`` forces the loop
(``testbed simulate --simulator per-sample``); a ``SimResult`` says which ran (``simulator``).
"""

from __future__ import annotations

import dataclasses
import math

import numba as nb
import numpy as np

from attackers.greedy import greedy_init, greedy_step

from .channel import LATE, loss_cause
from .flow import FLOW_OK, flow_into
from .methods.ends import unaware_update
from .quantizer import box_center, control_input, quantize_index, zoom_update
from .simloop import SCORES, Network, OnlineAttacker, SimResult, simulate_loop

#: ``simulate_scenario(simulator=...)``: "auto" (the kernel where it can run), "batch" (the kernel or an
#: error), "per-sample" (the loop always)
SIMULATORS = ("auto", "batch", "per-sample")
BATCH = "batch"
PER_SAMPLE = "per-sample"


@nb.njit(cache=True)
def _record_kernel(rhs, p, rhs_m, p_m, T, opts, Kgain, x0, E0, M, Lambda, mode, sigma, E_min, dpar, u_max,
                   theta_tab, tpar, lat, chan, greedy_params, g_init, score_kind, n_steps,
                   X, U, Q, QE, XIE, EE, XID, ED, TH, SYM, SAT, UMISS, DEL, x_final, state_final, info):
    # One trajectory of ``simulate._batch_kernel`` (the same statements in the same order, hence the same
    # numbers), keeping what ``simloop.simulate_loop`` records per sample.  info: [samples run, flow status,
    # non-finite inputs rejected, inputs clamped, overflows received].  chan (4, N): the channel per sample
    # (``channel.SampleChannel``): [the controller cannot receive it, upstream delay ns, u_k lost] and, written
    # here, the attacker's own decision
    n = x0.shape[0]
    m = Kgain.shape[0]
    K_s = np.empty((13, n))
    ytmp = np.empty(n)
    u = np.empty(m)
    u_e = np.empty(m)
    u_d = np.empty(m)
    up_e = np.zeros(m)
    up_d = np.zeros(m)
    u_held = np.zeros(m)
    u_app = np.empty(m)
    x = np.empty(n)
    xn = np.empty(n)
    xi_e = np.zeros(n)
    xi_d = np.zeros(n)
    xi_e_n = np.empty(n)
    xi_d_n = np.empty(n)
    zero = np.zeros(n)
    q_e = np.empty(n)
    q_d = np.empty(n)
    gstate = g_init.copy()
    use_greedy = greedy_params.shape[0] > 0
    physical = tpar[0] == 1
    n_codes_box = M ** n
    for i in range(n):
        x[i] = x0[i]
    E_e = E0
    E_d = E0
    if mode == 3 or mode == 5 or mode == 6:
        E_e = 0.0
        E_d = 0.0
    last = n_steps
    st = 0
    nrej = 0
    nclamp = 0
    novf = 0
    for k in range(n_steps):
        nrm = 0.0
        for i in range(n):
            nrm = max(nrm, abs(x[i]))
            X[k, i] = x[i]
            XIE[k, i] = xi_e[i]
            XID[k, i] = xi_d[i]
        EE[k] = E_e
        ED[k] = E_d
        # --- attacker
        if use_greedy:
            score = nrm if score_kind == 0 else E_e
            th = greedy_step(gstate, k, T, score, greedy_params)
        elif theta_tab.shape[0] > k:
            th = theta_tab[k]
        else:
            th = 0
        chan[3, k] = th
        if chan[0, k] != 0:
            th = 1
        TH[k] = th
        if mode == 5 or mode == 6:  # exact state feedback: the symbol is x_k itself (recorded as 0)
            SYM[k] = 0
            SAT[k] = False
            for i in range(n):
                QE[k, i] = x[i]
                Q[k, i] = x[i] if th == 0 else 0.0
            if mode == 5:
                control_input(Kgain, x, th, False, u)
                for r in range(m):
                    up_e[r] = u[r]
                    up_d[r] = u[r]
            elif th == 0:
                control_input(Kgain, x, 0, False, u)
                for r in range(m):
                    up_e[r] = u[r]
                    up_d[r] = u[r]
            else:
                for r in range(m):
                    u[r] = up_d[r]
        elif mode == 3:  # static: Q(0, R), R = E0
            idx, sat = quantize_index(x, zero, E0, M)
            SYM[k] = idx
            SAT[k] = sat
            box_center(idx, zero, E0, M, q_e)
            if th == 0:
                box_center(idx, zero, E0, M, q_d)
            else:
                for i in range(n):
                    q_d[i] = 0.0
            for i in range(n):
                QE[k, i] = q_e[i]
                Q[k, i] = q_d[i]
            control_input(Kgain, q_d, th, False, u)
            for r in range(m):
                up_d[r] = u[r]
        else:
            # --- encoder (Algorithm 1)
            idx, sat = quantize_index(x, xi_e, E_e, M)
            box_center(idx, xi_e, E_e, M, q_e)
            sym = idx
            if sat and (mode == 1 or mode == 4):
                sym = n_codes_box
            SYM[k] = sym
            SAT[k] = sat
            overflow = sym == n_codes_box
            # --- decoder / controller (Algorithm 2, law (2))
            if th == 0 and not overflow:
                box_center(sym, xi_d, E_d, M, q_d)
            else:
                for i in range(n):
                    q_d[i] = 0.0
            if th == 0 and overflow:
                novf += 1
            for i in range(n):
                QE[k, i] = q_e[i]
                Q[k, i] = q_d[i]
            control_input(Kgain, q_d, th, overflow, u)
            # --- both ends: rules (xi), (E) on the model
            if mode == 4:
                E_e_n, _s1 = unaware_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_e, E_e, q_e, up_e,
                                            Lambda, M, sigma, E_min, dpar, K_s, ytmp, u_e, xi_e_n)
                E_d_n, _s2 = unaware_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_d, E_d, q_d, up_d,
                                            Lambda, M, sigma, E_min, dpar, K_s, ytmp, u_d, xi_d_n)
            else:
                E_e_n, _s1 = zoom_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_e, E_e, q_e, up_e, Lambda,
                                         M, sigma, E_min, dpar, K_s, ytmp, u_e, xi_e_n)
                E_d_n, _s2 = zoom_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_d, E_d, q_d, up_d, Lambda,
                                         M, sigma, E_min, dpar, K_s, ytmp, u_d, xi_d_n)
            for i in range(n):
                xi_e[i] = xi_e_n[i]
                xi_d[i] = xi_d_n[i]
            for r in range(m):
                up_e[r] = u_e[r]
                up_d[r] = u_d[r]
            E_e = E_e_n
            E_d = E_d_n
        # --- the actuator (PlantProtocol.check_input): u_k as decided is recorded; a non-finite u_k is
        #     not applied, |u_k| is clamped to u_max
        bad = False
        big = False
        for r in range(m):
            U[k, r] = u[r]
            if not math.isfinite(u[r]):
                bad = True
            elif abs(u[r]) > u_max:
                big = True
        if bad:
            nrej += 1
            for r in range(m):
                u[r] = 0.0
        elif big:
            nclamp += 1
            for r in range(m):
                if u[r] > u_max:
                    u[r] = u_max
                elif u[r] < -u_max:
                    u[r] = -u_max
        # --- the true plant
        if physical:
            arr = lat[k] + (tpar[4] if th == 1 else chan[1, k])
            missing = bad or chan[2, k] != 0 or arr > tpar[3]
            if missing:
                dns = tpar[3]
            elif tpar[1] == 1:
                dns = max(max(arr, 0), tpar[2] if th == 0 else tpar[3])
            else:
                dns = max(arr, 0)
            for r in range(m):
                u_app[r] = 0.0 if missing else u[r]
            UMISS[k] = missing
            DEL[k] = dns
            dk = dns / 1e9
            st = flow_into(rhs, x, u_held, p, dk, opts, K_s, ytmp, xn)
            if st == 0:
                st = flow_into(rhs, xn, u_app, p, T - dk, opts, K_s, ytmp, xn)
            for r in range(m):
                u_held[r] = u_app[r]
        else:
            UMISS[k] = bad or chan[2, k] != 0
            if chan[2, k] != 0:
                for r in range(m):
                    u[r] = 0.0
            st = flow_into(rhs, x, u, p, T, opts, K_s, ytmp, xn)
        for i in range(n):
            x[i] = xn[i]
        if st != 0:
            last = k + 1
            break
    for i in range(n):
        x_final[i] = x[i]
        state_final[i] = xi_e[i]
        state_final[n + 1 + m + i] = xi_d[i]
    state_final[n] = E_e
    state_final[2 * n + 1 + m] = E_d
    for r in range(m):
        state_final[n + 1 + r] = up_e[r]
        state_final[2 * n + 2 + m + r] = up_d[r]
    info[0] = last
    info[1] = st
    info[2] = nrej
    info[3] = nclamp
    info[4] = novf


def _bundled(plant) -> bool:
    return type(plant).__module__.split(".")[0] == "plants" and hasattr(type(plant).rhs, "cfunc")


def kernel_refusal(sc, network: Network | None = None) -> str | None:
    """Why the batch kernel cannot run scenario ``sc`` (one phrase), or None when it can."""
    if sc.plant.fmu is not None:
        return "the true plant is an FMU"
    try:
        if not _bundled(sc.make_plant()) or not _bundled(sc.make_model()):
            return "the plant or the model is not a bundled plant"
    except Exception as e:  # noqa: BLE001 - whatever makes the plant fail, the per-sample loop reports it
        return f"the plant cannot be made here ({type(e).__name__})"
    method = sc.make_method()
    if method.kernel_code(sc.quantizer) is None:
        return f"method {method.display_name()!r} has no batch kernel (a user's method)"
    if network is not None and (network.ack_via_attacker or network.corrupt):
        return "acks via the attacker or corrupted payloads (only the protocol objects model them)"
    if sc.attack.online and sc.attack.kind != "greedy":
        return f"the online attacker {sc.attack.kind!r}"
    if network is not None and network.channel is not None and network.channel != sc.network:
        return "a channel other than the scenario's [network] (the kernel applies the scenario's)"
    if sc.network is not None and sc.attack.online and sc.attack.score == "E" and sc.network.link("ack").loss > 0:
        return "the greedy attacker scoring E with a lossy ack link (it reads the encoder's E while it withholds)"
    return None


class _Ledger:
    """An encoder end that only keeps the books: ``EncoderProtocol``'s counters of a kernel run with a
    channel come from the protocol object itself, fed the samples' fates (the numbers are the kernel's)."""

    xi = E = q = None
    saturations = 0

    def encode(self, x):
        return 0, False

    def ack(self, theta):
        pass


def _encoder_counters(chan, theta: np.ndarray, sat: np.ndarray, last: int) -> dict:
    """The encoder's counters (``EncoderProtocol.counters``) of a kernel run with a channel: the same
    protocol object driven as ``simloop.simulate_loop`` drives it (acks before the next sensor sample)."""
    from .protocol import EncoderProtocol

    encp = EncoderProtocol(_Ledger(), len(chan.sensed))
    acks: list = []
    last_rx = -1
    for k in range(last):
        for a in acks:
            encp.ack(*a)
        acks.clear()
        if chan.sensed[k]:
            encp.sensor(k, None)
        if theta[k] == 0:
            last_rx = k
        if not chan.ack_lost[k]:
            acks.append((k, int(theta[k]), last_rx))
    for a in acks:
        encp.ack(*a)
    out = encp.counters()
    out["saturations"] = int(sat.sum())
    return out


def simulate_kernel(sc, N: int, latency=None) -> SimResult:
    """Scenario ``sc`` for N samples on the recording kernel (``kernel_refusal(sc)`` must be None)."""
    plant, model = sc.make_plant(), sc.make_model()
    n, m = model.n, model.m
    qp = sc.quantizer
    method = sc.make_method()
    mode = int(method.kernel_code(qp))
    E0 = float(method.kernel_E0(qp))
    dpar = np.zeros(4) if mode == 4 else np.ascontiguousarray(qp.dpar, dtype=np.float64)
    K = np.ascontiguousarray(np.asarray(sc.K, dtype=np.float64).reshape(m, n))
    if sc.attack.online:
        gp = np.ascontiguousarray(sc.attack.greedy_params(), dtype=np.float64)
        tab = np.zeros(0, dtype=np.uint8)
    else:
        gp = np.zeros(0)
        th = sc.theta(N)
        tab = np.zeros(0, dtype=np.uint8) if th is None else np.ascontiguousarray(th, dtype=np.uint8)
    tpar = np.ascontiguousarray(sc.timing_params, dtype=np.int64)
    physical = bool(tpar[0])
    if latency is None:
        latency = sc.sim_latency(N)
    lat = np.broadcast_to(np.asarray(0 if latency is None else latency, dtype=np.int64), (N,))
    cb = method.codebook(n, qp)
    chan = Network(channel=sc.network).samples(N, tpar, n, m, cb.nbytes)
    ctab = np.zeros((4, N), dtype=np.int64)
    if chan is not None:
        ctab[0] = chan.forced
        ctab[1] = chan.upstream_ns
        ctab[2] = chan.actuation_lost
        lat = lat + chan.actuation_ns
    lat = np.ascontiguousarray(lat)
    a = {k: np.zeros((N, n)) for k in ("x", "q", "q_enc", "xi_enc", "xi_dec")}
    U = np.zeros((N, m))
    EE, ED = np.zeros(N), np.zeros(N)
    TH = np.zeros(N, dtype=np.uint8)
    SYM = np.zeros(N, dtype=np.int64)
    SAT = np.zeros(N, dtype=bool)
    UMISS = np.zeros(N, dtype=bool)
    DEL = np.zeros(N, dtype=np.int64)
    x_final = np.zeros(n)
    W = 2 * (n + 1 + m)
    state_final = np.zeros(W)
    info = np.zeros(5, dtype=np.int64)
    _record_kernel(type(plant).rhs.cfunc, plant.p, type(model).rhs.cfunc, model.p, float(qp.T), sc.flow.as_array(),
                   K, np.ascontiguousarray(sc.x0, dtype=np.float64), E0, int(qp.M), float(qp.Lambda), mode,
                   float(qp.sigma), float(qp.E_min), dpar, float(sc.controller.u_max), tab, tpar, lat, ctab, gp,
                   greedy_init(), SCORES[sc.attack.score], N, a["x"], U, a["q"], a["q_enc"], a["xi_enc"], EE,
                   a["xi_dec"], ED, TH, SYM, SAT, UMISS, DEL, x_final, state_final, info)
    last, status, nrej, nclamp, novf = (int(v) for v in info)
    sl = slice(0, last)
    theta = TH[sl].copy()
    lost = int(theta.sum())
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
        enc_counters = _encoder_counters(chan, theta, sat, last)
        c = {"sensed": chan.sensed[sl], "symbol_lost": chan.symbol_lost[sl], "late": chan.late[sl]}
    cause = loss_cause(theta, withheld=withheld, attacker=ctab[3, sl] != 0, **c)
    counters = {"encoder": enc_counters,
                "controller": {"received": last - lost, "lost_deadline": lost, "invalid": 0,
                               "late": int(np.count_nonzero(cause == LATE)),
                               "superseded": 0, "future": 0, "overflows": novf, "decided": last},
                "plant": {"rejected_nonfinite": nrej, "clamped": nclamp}}
    return SimResult(T=qp.T, t=np.arange(last) * qp.T, x=a["x"][sl], u=U[sl], q=a["q"][sl], q_enc=a["q_enc"][sl],
                     xi_enc=a["xi_enc"][sl], E_enc=EE[sl], xi_dec=a["xi_dec"][sl], E_dec=ED[sl], theta=theta,
                     symbols=SYM[sl], saturated=sat, x_final=x_final,
                     flow_status=FLOW_OK if status == 0 else status, diverged_at=-1 if status == 0 else last - 1, K=K,
                     reason=theta.astype(np.int64), withheld=withheld, u_missing=UMISS[sl], loss_cause=cause,
                     delays=DEL[sl].copy() if physical else None, counters=counters, loop_state=state_final,
                     simulator=BATCH)


def simulate_scenario(sc, *, n_steps: int | None = None, network: Network | None = None,
                      latency=None, simulator: str = "auto") -> SimResult:
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
        network = dataclasses.replace(network or Network(), channel=sc.network)
    if simulator != PER_SAMPLE:
        why = kernel_refusal(sc, network)
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
                             u_max=sc.controller.u_max, network=network, method=sc.make_method())
    finally:
        process.close()
