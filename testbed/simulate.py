"""In-process simulators: plant, encoder, attacker and decoder/controller in lockstep.

Two entry points share one semantics (sample k = 0, ..., N-1 at t_k = k T):

1. ``simulate_loop`` - one trajectory, per sample, with *separate* ``Encoder`` and
   ``Decoder`` objects that only see symbols and acks (what a live run does).
   Returns every per-sample quantity (``SimResult``).
2. ``simulate_batch`` - many initial states and/or schedules at once in one
   numba kernel (one core).  Encoder and decoder keep separate (xi, E) arrays and
   each computes its own prediction; their disagreement is counted.  Summary
   outputs always, full traces on request.  The analysis uses this.

At every sample:  x_k -> encoder symbol (Algorithm 1) -> attacker (theta_k) ->
decoder q_k, u_k = (1 - theta_k) K q_k (Algorithm 2, law (2)) -> ack theta_k ->
both ends apply (xi), (E) -> plant x_{k+1} = phi_T(x_k, u_k).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba as nb
import numpy as np

from attackers.greedy import greedy_init, greedy_step

from .flow import DEFAULT_FLOW, FLOW_OK, FlowOptions, flow_into, phi_T
from .quantizer import (MODES, Codebook, Decoder, Encoder, QuantizerParams,
                        box_center, control_input, quantize_index, zoom_update)

SCORE_STATE = 0  # greedy attacker hurts where ||x_k||_inf is largest
SCORE_E = 1      # ... or where E_k is largest
SCORES = {"state": SCORE_STATE, "E": SCORE_E}


# ============================================================================ per-sample loop
@dataclass
class SimResult:
    """Per-sample record of one closed-loop run (arrays indexed by k = 0..N-1)."""

    T: float
    t: np.ndarray
    x: np.ndarray          # x_k, (N, n)
    u: np.ndarray          # u_k, (N, m)
    q: np.ndarray          # q_k at the decoder (0 when lost), (N, n)
    q_enc: np.ndarray      # q_k at the encoder (centre of the box of x_k), (N, n)
    xi_enc: np.ndarray     # xi_k at the encoder, (N, n)
    E_enc: np.ndarray      # E_k at the encoder, (N,)
    xi_dec: np.ndarray
    E_dec: np.ndarray
    theta: np.ndarray      # theta_k (1: packet lost), (N,) uint8
    symbols: np.ndarray    # symbol sent by the encoder, (N,) int64
    saturated: np.ndarray  # x_k outside Q(xi_k, E_k) at the encoder, (N,) bool
    x_final: np.ndarray    # x_N
    flow_status: int = FLOW_OK   # first non-ok flow status of the plant, if any
    diverged_at: int = -1        # sample at which the plant flow diverged, or -1
    K: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))

    @property
    def saturations(self) -> int:
        return int(self.saturated.sum())

    @property
    def final_norm(self) -> float:
        return float(np.max(np.abs(self.x_final)))

    @property
    def agree(self) -> bool:
        """Encoder and decoder xi_k, E_k identical at every sample (bit for bit)."""
        return bool(np.array_equal(self.xi_enc, self.xi_dec) and np.array_equal(self.E_enc, self.E_dec))

    def intervals(self):
        """The realized DoS schedule (runs of lost samples) as (start, length) pairs."""
        from attackers.schedule import Schedule

        return Schedule.from_theta(self.theta, self.T)


class OnlineAttacker:
    """theta_k from a precomputed 0/1 sequence or from the greedy policy (online)."""

    def __init__(self, theta=None, greedy_params=None, score: str = "state", T: float = 0.1):
        self.theta = None if theta is None else np.asarray(theta, dtype=np.uint8)
        self.greedy_params = None if greedy_params is None else np.asarray(greedy_params, dtype=np.float64)
        self.score = SCORES[score]
        self.T = T
        self._gstate = greedy_init()

    def decide(self, k: int, x_k, E_k) -> int:
        if self.greedy_params is not None:
            s = float(np.max(np.abs(x_k))) if self.score == SCORE_STATE else float(E_k)
            return int(greedy_step(self._gstate, k, self.T, s, self.greedy_params))
        if self.theta is None or k >= len(self.theta):
            return 0
        return int(self.theta[k])


def simulate_loop(plant, K, qp: QuantizerParams, x0, n_steps: int, attacker: OnlineAttacker,
                  flow: FlowOptions = DEFAULT_FLOW) -> SimResult:
    """One trajectory, sample by sample, with separate Encoder and Decoder objects."""
    n, m = plant.n, plant.m
    K = np.asarray(K, dtype=np.float64).reshape(m, n)
    enc = Encoder(plant, K, qp, flow)
    dec = Decoder(plant, K, qp, flow)
    N = int(n_steps)
    rec = {k: np.zeros((N, n)) for k in ("x", "q", "q_enc", "xi_enc", "xi_dec")}
    u_rec = np.zeros((N, m))
    E_enc = np.zeros(N)
    E_dec = np.zeros(N)
    theta = np.zeros(N, dtype=np.uint8)
    symbols = np.zeros(N, dtype=np.int64)
    sat = np.zeros(N, dtype=bool)
    x = np.asarray(x0, dtype=np.float64).copy()
    status, diverged_at = FLOW_OK, -1
    last = N
    for k in range(N):
        rec["x"][k] = x
        rec["xi_enc"][k] = enc.xi
        rec["xi_dec"][k] = dec.xi
        E_enc[k] = enc.E
        E_dec[k] = dec.E
        sym, s = enc.encode(x)
        symbols[k], sat[k] = sym, s
        rec["q_enc"][k] = enc.q
        drop = attacker.decide(k, x, enc.E)
        u, q, th = dec.step(None if drop else sym)
        enc.ack(th)
        theta[k] = th
        rec["q"][k] = q
        u_rec[k] = u
        x_next, st = phi_T(plant, x, u, qp.T, flow)
        x = x_next
        if st != FLOW_OK:
            status, diverged_at, last = int(st), k, k + 1
            break
    sl = slice(0, last)
    return SimResult(T=qp.T, t=np.arange(last) * qp.T, x=rec["x"][sl], u=u_rec[sl], q=rec["q"][sl],
                     q_enc=rec["q_enc"][sl], xi_enc=rec["xi_enc"][sl], E_enc=E_enc[sl],
                     xi_dec=rec["xi_dec"][sl], E_dec=E_dec[sl], theta=theta[sl], symbols=symbols[sl],
                     saturated=sat[sl], x_final=x, flow_status=status, diverged_at=diverged_at, K=K)


# ============================================================================ batch kernel
@nb.njit(cache=True)
def _batch_kernel(rhs, p, T, opts, Kgain, X0, E0, M, Lambda, mode, sigma, E_min,
                  theta_tab, sched_idx, greedy_params, g_init, score_kind, n_steps, record,
                  X_rec, E_rec, th_rec, x_final, E_final, status, stop_k, sat_count,
                  mismatch, max_norm, theta_count):
    B = X0.shape[0]
    n = X0.shape[1]
    m = Kgain.shape[0]
    K_s = np.empty((13, n))
    ytmp = np.empty(n)
    u = np.empty(m)
    u_s = np.empty(m)
    x = np.empty(n)
    xn = np.empty(n)
    xi_e = np.empty(n)
    xi_d = np.empty(n)
    xi_e_n = np.empty(n)
    xi_d_n = np.empty(n)
    q_e = np.empty(n)
    q_d = np.empty(n)
    gstate = np.empty(g_init.shape[0])
    use_greedy = greedy_params.shape[0] > 0  # (B, 5): one budget per trajectory
    n_codes_box = M ** n
    for b in range(B):
        for i in range(n):
            x[i] = X0[b, i]
            xi_e[i] = 0.0
            xi_d[i] = 0.0
        E_e = E0
        E_d = E0
        if use_greedy:
            for i in range(gstate.shape[0]):
                gstate[i] = g_init[i]
        srow = sched_idx[b]
        st = 0
        stop_k[b] = n_steps
        nsat = 0
        nmis = 0
        nth = 0
        mx = 0.0
        for k in range(n_steps):
            nrm = 0.0
            for i in range(n):
                nrm = max(nrm, abs(x[i]))
            mx = max(mx, nrm)
            if record:
                for i in range(n):
                    X_rec[b, k, i] = x[i]
                E_rec[b, k] = E_e
            # --- attacker
            if use_greedy:
                score = nrm if score_kind == 0 else E_e
                th = greedy_step(gstate, k, T, score, greedy_params[b])
            elif theta_tab.shape[1] > k:
                th = theta_tab[srow, k]
            else:
                th = 0
            nth += th
            if record:
                th_rec[b, k] = th
            if mode == 2:  # no quantization: u_k = (1 - theta_k) K x_k
                control_input(Kgain, x, th, False, u)
            else:
                # --- encoder (Algorithm 1)
                idx, sat = quantize_index(x, xi_e, E_e, M)
                box_center(idx, xi_e, E_e, M, q_e)
                sym = idx
                if sat:
                    nsat += 1
                    if mode == 1:
                        sym = n_codes_box
                overflow = sym == n_codes_box
                # --- decoder / controller (Algorithm 2, law (2))
                if th == 0 and not overflow:
                    box_center(sym, xi_d, E_d, M, q_d)
                else:
                    for i in range(n):
                        q_d[i] = 0.0
                control_input(Kgain, q_d, th, overflow, u)
                # --- both ends: rules (xi), (E); each computes its own prediction
                E_e_n, _s1 = zoom_update(rhs, p, T, opts, Kgain, th, overflow, xi_e, E_e, q_e, Lambda,
                                         M, sigma, E_min, K_s, ytmp, u_s, xi_e_n)
                E_d_n, _s2 = zoom_update(rhs, p, T, opts, Kgain, th, overflow, xi_d, E_d, q_d, Lambda,
                                         M, sigma, E_min, K_s, ytmp, u_s, xi_d_n)
                same = E_e_n == E_d_n
                for i in range(n):
                    xi_e[i] = xi_e_n[i]
                    xi_d[i] = xi_d_n[i]
                    if xi_e_n[i] != xi_d_n[i]:
                        same = False
                E_e = E_e_n
                E_d = E_d_n
                if not same:
                    nmis += 1
            # --- plant
            st = flow_into(rhs, x, u, p, T, opts, K_s, ytmp, xn)
            for i in range(n):
                x[i] = xn[i]
            if st != 0:
                stop_k[b] = k + 1
                break
        nrm = 0.0
        for i in range(n):
            nrm = max(nrm, abs(x[i]))
            x_final[b, i] = x[i]
        max_norm[b] = max(mx, nrm)
        E_final[b] = E_e
        status[b] = st
        sat_count[b] = nsat
        mismatch[b] = nmis
        theta_count[b] = nth


@dataclass
class BatchResult:
    """Summary (always) and traces (``record=True``) of a batch run."""

    x_final: np.ndarray     # (B, n)
    E_final: np.ndarray     # (B,)
    status: np.ndarray      # (B,) FLOW_* of the plant at the stop
    stop_k: np.ndarray      # (B,) samples simulated (n_steps unless the flow diverged)
    saturations: np.ndarray  # (B,)
    mismatch: np.ndarray    # (B,) samples where encoder and decoder disagreed
    max_norm: np.ndarray    # (B,) max ||x_k||_inf over the run
    attacked: np.ndarray    # (B,) number of samples with theta_k = 1
    x: np.ndarray | None = None      # (B, N, n) x_k
    E: np.ndarray | None = None      # (B, N) E_k at the encoder
    theta: np.ndarray | None = None  # (B, N)

    @property
    def final_norm(self) -> np.ndarray:
        return np.max(np.abs(self.x_final), axis=1)

    def converged(self, tol: float = 1e-4) -> np.ndarray:
        return (self.status == FLOW_OK) & (self.final_norm < tol)


def simulate_batch(plant, K, qp: QuantizerParams, X0, n_steps: int, *, theta=None, sched_idx=None,
                   greedy_params=None, score: str = "state", mode: str | None = None,
                   record: bool = False, flow: FlowOptions = DEFAULT_FLOW,
                   specialize: bool = False) -> BatchResult:
    """Vectorized lockstep simulation of B trajectories (numba, one core).

    Parameters
    ----------
    plant, K, qp : the loop (K is m x n)
    X0 : (B, n) initial states (or (n,) for one)
    n_steps : number of samples N
    theta : (S, N') 0/1 attack table, S schedules (rows shorter than N are padded
        with 0); ``sched_idx`` (B,) picks each trajectory's row (default: row b if
        S == B, else row 0).  None: no attack.
    greedy_params : [kappa_F, rho_F, kappa_D, rho_D, threshold] (shape (5,), or (B, 5)
        for one budget per trajectory) to run the online greedy attacker instead (``score`` "state" or "E" is what it maximizes).
    mode : "ideal" | "resilient" | "none" (no quantization: the nominal loop);
        default qp.mode.
    record : keep x_k, E_k and theta_k for every sample.
    specialize : compile the kernel for this plant (its right-hand side inlined):
        about twice the throughput, but a few seconds of compilation in every
        new process (numba cannot cache it).  Worth it for big grids and sweeps.
        Results are identical either way.
    """
    X0 = np.ascontiguousarray(np.atleast_2d(np.asarray(X0, dtype=np.float64)))
    B, n = X0.shape
    if n != plant.n:
        raise ValueError(f"X0 has {n} columns, plant {plant.name} has n = {plant.n}")
    N = int(n_steps)
    Kg = np.ascontiguousarray(np.asarray(K, dtype=np.float64).reshape(plant.m, plant.n))
    if theta is None:
        tab = np.zeros((1, 0), dtype=np.uint8)
    else:
        tab = np.ascontiguousarray(np.atleast_2d(np.asarray(theta, dtype=np.uint8)))
    if sched_idx is None:
        sched_idx = np.arange(B) if tab.shape[0] == B else np.zeros(B, dtype=np.int64)
    sched_idx = np.ascontiguousarray(np.broadcast_to(np.asarray(sched_idx, dtype=np.int64), (B,)))
    if sched_idx.size and (sched_idx.max() >= tab.shape[0] or sched_idx.min() < 0):
        raise ValueError("sched_idx points outside the theta table")
    if greedy_params is None:
        gp = np.zeros((0, 5))
    else:
        gp = np.asarray(greedy_params, dtype=np.float64)
        gp = np.ascontiguousarray(np.broadcast_to(gp, (B, 5)) if gp.ndim == 1 else gp)
        if gp.shape != (B, 5):
            raise ValueError(f"greedy_params must have shape (5,) or ({B}, 5), got {gp.shape}")
    mode_code = MODES[mode or qp.mode]
    shp = (B, N) if record else (0, 0)
    X_rec = np.zeros(shp + (n,)) if record else np.zeros((0, 0, n))
    E_rec = np.zeros(shp)
    th_rec = np.zeros(shp, dtype=np.uint8)
    out = dict(x_final=np.zeros((B, n)), E_final=np.zeros(B), status=np.zeros(B, np.int8),
               stop_k=np.zeros(B, np.int64), saturations=np.zeros(B, np.int64),
               mismatch=np.zeros(B, np.int64), max_norm=np.zeros(B), attacked=np.zeros(B, np.int64))
    rhs = type(plant).rhs.jit if specialize else type(plant).rhs.cfunc
    _batch_kernel(rhs, plant.p, float(qp.T), flow.as_array(), Kg, X0, float(qp.E0), int(qp.M),
                  float(qp.Lambda), mode_code, float(qp.sigma), float(qp.E_min), tab, sched_idx, gp, greedy_init(),
                  SCORES[score], N, bool(record), X_rec, E_rec, th_rec, out["x_final"], out["E_final"],
                  out["status"], out["stop_k"], out["saturations"], out["mismatch"], out["max_norm"],
                  out["attacked"])
    res = BatchResult(**out)
    if record:
        res.x, res.E, res.theta = X_rec, E_rec, th_rec
    return res


# ============================================================================ scenario level
def in_nominal_roa(plant, K, T: float, X, horizon: float = 60.0, tol: float = 1e-4,
                   flow: FlowOptions = DEFAULT_FLOW) -> np.ndarray:
    """Whether each state of X (B, n) lies in the nominal region of attraction.

    Nominal: no quantization and no DoS, u_k = K x_k (sampled data, held for T).
    A state is in the region when the nominal loop from it reaches
    ||x||_inf < tol within ``horizon`` seconds.
    """
    qp = QuantizerParams(T=T, M=2, L=0.0, E0=1.0, mode="none")
    res = simulate_batch(plant, K, qp, X, int(round(horizon / T)), mode="none", flow=flow)
    return res.converged(tol)


def simulate_scenario(sc, *, n_steps: int | None = None) -> SimResult:
    """Run a scenario (see ``testbed.scenario``) with the per-sample loop."""
    plant = sc.make_plant()
    N = sc.n_steps if n_steps is None else int(n_steps)
    if sc.attack.online:
        att = OnlineAttacker(greedy_params=sc.attack.greedy_params(), score=sc.attack.score, T=sc.T)
    else:
        att = OnlineAttacker(theta=sc.theta(N), T=sc.T)
    return simulate_loop(plant, sc.K, sc.quantizer, sc.x0, N, att, sc.flow)


def summarize(sc, res: SimResult, *, arrays: bool = False) -> dict:
    """The JSON document of ``testbed simulate --json`` (keys shared with ``testbed report``).

    ``arrays``: the per-sample values stay numpy arrays (``testbed report`` streams them out).
    """
    L = (lambda a: a) if arrays else (lambda a: a.tolist())
    plant = sc.make_plant()
    tol = sc.run.converge_tol
    diverged = res.flow_status != FLOW_OK
    converged = (not diverged) and res.final_norm < tol
    escaped = diverged or not bool(in_nominal_roa(plant, res.K, sc.T, res.x_final[None, :], tol=tol,
                                                   flow=sc.flow)[0])
    sch = res.intervals()
    cb = Codebook(plant.n, sc.quantizer.M, resilient=(sc.quantizer.mode == "resilient"))
    return {
        "scenario": sc.name,
        "plant": plant.name,
        "n": plant.n,
        "m": plant.m,
        "T": sc.T,
        "M": sc.quantizer.M,
        "Lambda": sc.quantizer.Lambda,
        "mode": sc.quantizer.mode,
        "bits": cb.bits,
        "K": res.K.tolist(),
        "t": L(res.t),
        "x": L(res.x),
        "u": L(res.u),
        "q": L(res.q),
        "xi": L(res.xi_enc),
        "E": L(res.E_enc),
        "E_dec": L(res.E_dec),
        "theta": res.theta if arrays else res.theta.astype(int).tolist(),
        "symbols": L(res.symbols),
        "saturations": res.saturations,
        "saturated_at": L(np.nonzero(res.saturated)[0]),
        "dos_intervals": [list(iv) for iv in sch.intervals],
        "packets_dropped": int(res.theta.sum()),
        "encoder_decoder_agree": res.agree,
        "x_final": res.x_final.tolist(),
        "final_norm": res.final_norm,
        "converged": bool(converged),
        "escaped": bool(escaped),
        "diverged": bool(diverged),
        "diverged_at": res.diverged_at,
    }
