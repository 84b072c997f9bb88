"""The compiled loop: one numba kernel for the batch simulator and the scenario simulator.

``simulate.simulate_batch`` runs it over many trajectories for their summaries (what the
analysis runs, optionally with x_k, E_k and theta_k); ``trajectory.simulate_kernel`` runs it over
one trajectory with every per-sample array of a ``SimResult`` (``trace``) and a ``[network]``
channel (``chan``).  One kernel, so both compute the same numbers from one definition.

At every sample:  x_k -> encoder symbol (Algorithm 1) -> attacker (theta_k) ->
decoder q_k, u_k = (1 - theta_k) K q_k (Algorithm 2, law (2)) -> ack theta_k ->
both ends apply (xi), (E) -> actuator -> plant x_{k+1} = phi_T(x_k, u_k).

The method codes (``mode``, ``methods.bundled``): 0, 1 the paper's ideal and resilient quantizer,
2 no quantization (the nominal loop), 3 static, 4 zoom, 5 unquantized, 6 unquantized-hold.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from attackers.greedy import greedy_step

from ..loop.flow import flow_into
from ..loop.quantizer import box_center, control_input, quantize_index, zoom_update
from ..methods.ends import unaware_update

#: the kernel parameters that carry a right-hand side (the true plant's, the model's): the cached
#: specialized kernel (``testbed.sim.kernelcache``) turns each into a global bound to a plant's ``RHS.jit``
_RHS_ARGS = ("rhs", "rhs_m")

#: ``trace`` (B, N, TRACE_INTS) of the full record: the symbol sent, saturated, u_k missing at the
#: plant, delta_k [ns] (physical timing)
TRACE_INTS = 4
#: ``counts`` (B, 3): non-finite inputs rejected, inputs clamped, OVERFLOWs received
COUNTS = 3


def loop_state_width(n: int, m: int) -> int:
    """Width W of a packed loop state: [xi_e (n), E_e, u_e (m), xi_d (n), E_d, u_d (m)], i.e.
    xi_k, E_k and u_{k-1} as the encoder and as the decoder know them."""
    return 2 * (n + 1 + m)


def trace_width(n: int, m: int) -> int:
    """Width of ``trace_f`` (B, N, .): [q_k (n), q_k at the encoder (n), xi_enc (n), xi_dec (n), u_k as
    decided (m), E_dec]."""
    return 4 * n + m + 1


@nb.njit(cache=True)
def _batch_kernel(rhs, p, rhs_m, p_m, T, opts, Kgain, X0, E0, M, Lambda, mode, sigma, E_min,
                  dpar, u_max, theta_tab, sched_idx, tpar, lat_tab, lat_idx,
                  greedy_params, g_init, score_kind, n_steps, record,
                  X_rec, E_rec, th_rec, x_final, E_final, status, stop_k, sat_count,
                  mismatch, max_norm, theta_count, init_state, stop_par, state_final,
                  chan, trace_f, trace_i, counts):
    # init_state (B, W) or (0, W): both ends' state to start from (``loop_state_width`` layout) instead of
    # xi_0 = 0, E_0, u_{-1} = 0; stop_par [x_tol, E_tol, x_out]: with x_tol > 0, a trajectory stops
    # at the first sample with ||x_k|| < x_tol and both E_k < E_tol, or with ||x_k|| > x_out
    # (the continuation of ``EscapeCriterion``); state_final (B, W): both ends' state at the stop.
    # chan (4, N) or (4, 0): a channel per sample (``channel.SampleChannel``, one trajectory): [the controller
    # cannot receive it, upstream delay ns, u_k lost] and, written here, the attacker's own decision.
    # trace_f (B, N, ``trace_width``), trace_i (B, N, TRACE_INTS) or (0, 0, .): the full record
    # (with ``record``); counts (B, COUNTS).
    B = X0.shape[0]
    n = X0.shape[1]
    m = Kgain.shape[0]
    K_s = np.empty((13, n))
    ytmp = np.empty(n)
    u = np.empty(m)
    u_e = np.empty(m)
    u_d = np.empty(m)
    up_e = np.empty(m)      # u_{k-1} as the encoder knows it
    up_d = np.empty(m)      # ... as the decoder knows it
    u_held = np.empty(m)    # u_{k-1} as the plant holds it (physical timing)
    x = np.empty(n)
    xn = np.empty(n)
    xi_e = np.empty(n)
    xi_d = np.empty(n)
    xi_e_n = np.empty(n)
    xi_d_n = np.empty(n)
    zero = np.zeros(n)
    q_e = np.empty(n)
    q_d = np.empty(n)
    gstate = np.empty(g_init.shape[0])
    use_greedy = greedy_params.shape[0] > 0  # (B, 5): one budget per trajectory
    physical = tpar[0] == 1                  # physical timing: u_{k-1} held for delta_k (PlantProtocol)
    has_chan = chan.shape[1] > 0
    full = trace_f.shape[0] > 0
    u_app = np.empty(m)
    n_codes_box = M ** n
    from_state = init_state.shape[0] > 0
    x_tol = stop_par[0]
    for b in range(B):
        for i in range(n):
            x[i] = X0[b, i]
            xi_e[i] = 0.0
            xi_d[i] = 0.0
        for r in range(m):
            up_e[r] = 0.0
            up_d[r] = 0.0
            u_held[r] = 0.0
        E_e = E0
        E_d = E0
        if mode == 3 or mode == 5 or mode == 6:  # static (E0 is its range), unquantized: no zoom state
            E_e = 0.0
            E_d = 0.0
        if from_state:
            for i in range(n):
                xi_e[i] = init_state[b, i]
                xi_d[i] = init_state[b, n + 1 + m + i]
            E_e = init_state[b, n]
            E_d = init_state[b, 2 * n + 1 + m]
            for r in range(m):
                up_e[r] = init_state[b, n + 1 + r]
                up_d[r] = init_state[b, 2 * n + 2 + m + r]
        if use_greedy:
            for i in range(gstate.shape[0]):
                gstate[i] = g_init[i]
        srow = sched_idx[b]
        drow = lat_idx[b] if physical else 0
        st = 0
        stop_k[b] = n_steps
        nsat = 0
        nmis = 0
        nth = 0
        nrej = 0
        nclamp = 0
        novf = 0
        mx = 0.0
        for k in range(n_steps):
            nrm = 0.0
            for i in range(n):
                nrm = max(nrm, abs(x[i]))
            if x_tol > 0.0 and ((nrm < x_tol and E_e < stop_par[1] and E_d < stop_par[1]) or nrm > stop_par[2]):
                stop_k[b] = k
                break
            mx = max(mx, nrm)
            if record:
                for i in range(n):
                    X_rec[b, k, i] = x[i]
                E_rec[b, k] = E_e
                if full:
                    for i in range(n):
                        trace_f[b, k, 2 * n + i] = xi_e[i]
                        trace_f[b, k, 3 * n + i] = xi_d[i]
                    trace_f[b, k, 4 * n + m] = E_d
            # --- attacker
            if use_greedy:
                score = nrm if score_kind == 0 else E_e
                th = greedy_step(gstate, k, T, score, greedy_params[b])
            elif theta_tab.shape[1] > k:
                th = theta_tab[srow, k]
            else:
                th = 0
            if has_chan:
                chan[3, k] = th
                if chan[0, k] != 0:  # the controller cannot receive this sample
                    th = 1
            nth += th
            if record:
                th_rec[b, k] = th
            if mode == 2:  # no quantization: u_k = (1 - theta_k) K x_k
                control_input(Kgain, x, th, False, u)
            elif mode == 5 or mode == 6:  # exact state feedback: the symbol is x_k itself (recorded as 0)
                if full:
                    for i in range(n):
                        trace_f[b, k, n + i] = x[i]
                        trace_f[b, k, i] = x[i] if th == 0 else 0.0
                if mode == 5:  # method unquantized: u_k = (1 - theta_k) K x_k, both ends keep u_k
                    control_input(Kgain, x, th, False, u)
                    for r in range(m):
                        up_e[r] = u[r]
                        up_d[r] = u[r]
                elif th == 0:  # method unquantized-hold: u_k = K x_k, or u_{k-1} through a loss
                    control_input(Kgain, x, 0, False, u)
                    for r in range(m):
                        up_e[r] = u[r]
                        up_d[r] = u[r]
                else:
                    for r in range(m):
                        u[r] = up_d[r]
            elif mode == 3:  # method static: Q(0, R) with R = E0, M levels, no zoom
                idx, sat = quantize_index(x, zero, E0, M)
                if sat:
                    nsat += 1
                if th == 0:
                    box_center(idx, zero, E0, M, q_d)
                else:
                    for i in range(n):
                        q_d[i] = 0.0
                control_input(Kgain, q_d, th, False, u)
                for r in range(m):
                    up_d[r] = u[r]
                if full:
                    box_center(idx, zero, E0, M, q_e)
                    trace_i[b, k, 0] = idx
                    trace_i[b, k, 1] = sat
                    for i in range(n):
                        trace_f[b, k, i] = q_d[i]
                        trace_f[b, k, n + i] = q_e[i]
            else:
                # --- encoder (Algorithm 1)
                idx, sat = quantize_index(x, xi_e, E_e, M)
                box_center(idx, xi_e, E_e, M, q_e)
                sym = idx
                if sat:
                    nsat += 1
                    if mode == 1 or mode == 4:
                        sym = n_codes_box
                overflow = sym == n_codes_box
                # --- decoder / controller (Algorithm 2, law (2))
                if th == 0 and not overflow:
                    box_center(sym, xi_d, E_d, M, q_d)
                else:
                    for i in range(n):
                        q_d[i] = 0.0
                if th == 0 and overflow:
                    novf += 1
                control_input(Kgain, q_d, th, overflow, u)
                if full:
                    trace_i[b, k, 0] = sym
                    trace_i[b, k, 1] = sat
                    for i in range(n):
                        trace_f[b, k, i] = q_d[i]
                        trace_f[b, k, n + i] = q_e[i]
                # --- both ends: rules (xi), (E) on the model; each computes its own prediction
                if mode == 4:  # method zoom: the zoom-in whatever theta_k (``methods.bundled.unaware_update``)
                    E_e_n, _s1 = unaware_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_e, E_e, q_e, up_e,
                                                Lambda, M, sigma, E_min, dpar, K_s, ytmp, u_e, xi_e_n)
                    E_d_n, _s2 = unaware_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_d, E_d, q_d, up_d,
                                                Lambda, M, sigma, E_min, dpar, K_s, ytmp, u_d, xi_d_n)
                else:
                    E_e_n, _s1 = zoom_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_e, E_e, q_e, up_e, Lambda,
                                             M, sigma, E_min, dpar, K_s, ytmp, u_e, xi_e_n)
                    E_d_n, _s2 = zoom_update(rhs_m, p_m, T, opts, Kgain, th, overflow, xi_d, E_d, q_d, up_d, Lambda,
                                             M, sigma, E_min, dpar, K_s, ytmp, u_d, xi_d_n)
                same = E_e_n == E_d_n
                for i in range(n):
                    xi_e[i] = xi_e_n[i]
                    xi_d[i] = xi_d_n[i]
                    if xi_e_n[i] != xi_d_n[i]:
                        same = False
                for r in range(m):
                    up_e[r] = u_e[r]
                    up_d[r] = u_d[r]
                    if u_e[r] != u_d[r]:
                        same = False
                E_e = E_e_n
                E_d = E_d_n
                if not same:
                    nmis += 1
            # --- the actuator (PlantProtocol.check_input): u_k as decided is recorded; a non-finite u_k is
            #     not applied, |u_k| is clamped to u_max
            bad = False
            big = False
            for r in range(m):
                if full:
                    trace_f[b, k, 4 * n + r] = u[r]
                if not math.isfinite(u[r]):
                    bad = True
                elif u[r] > u_max:
                    u[r] = u_max
                    big = True
                elif u[r] < -u_max:
                    u[r] = -u_max
                    big = True
            if bad:
                nrej += 1
                for r in range(m):
                    u[r] = 0.0
            elif big:
                nclamp += 1
            lost = has_chan and chan[2, k] != 0  # the channel lost u_k
            # --- the true plant: ideal timing phi_T(x_k, u_k); physical timing
            #     phi_{T - delta_k}(phi_delta_k(x_k, u_{k-1}), u_k)
            if physical:  # PlantProtocol.delay_ns: arrival of u_k, then the actuation policy
                arr = lat_tab[drow, k] + (tpar[4] if th == 1 else (chan[1, k] if has_chan else 0))
                missing = bad or lost or arr > tpar[3]
                if missing:
                    dns = tpar[3]
                elif tpar[1] == 1:
                    dns = max(max(arr, 0), tpar[2] if th == 0 else tpar[3])
                else:
                    dns = max(arr, 0)
                if full:
                    trace_i[b, k, 2] = missing
                    trace_i[b, k, 3] = dns
                for r in range(m):
                    u_app[r] = 0.0 if missing else u[r]
                dk = dns / 1e9
                st = flow_into(rhs, x, u_held, p, dk, opts, K_s, ytmp, xn)
                if st == 0:
                    st = flow_into(rhs, xn, u_app, p, T - dk, opts, K_s, ytmp, xn)
                for r in range(m):
                    u_held[r] = u_app[r]
            else:
                if full:
                    trace_i[b, k, 2] = bad or lost
                if lost:
                    for r in range(m):
                        u[r] = 0.0
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
        for i in range(n):
            state_final[b, i] = xi_e[i]
            state_final[b, n + 1 + m + i] = xi_d[i]
        state_final[b, n] = E_e
        state_final[b, 2 * n + 1 + m] = E_d
        for r in range(m):
            state_final[b, n + 1 + r] = up_e[r]
            state_final[b, 2 * n + 2 + m + r] = up_d[r]
        status[b] = st
        sat_count[b] = nsat
        mismatch[b] = nmis
        theta_count[b] = nth
        counts[b, 0] = nrej
        counts[b, 1] = nclamp
        counts[b, 2] = novf
