"""Assemble a run's summary from its per-sample telemetry: shared by ``testbed run`` and ``testbed report``.

The live launcher feeds it what its collector received over Zenoh; ``testbed
report`` feeds it what a recording holds, so both print the same keys.  The
per-sample arrays become a ``SimResult`` and go through
``testbed.simulate.summarize``, so every key of ``testbed simulate --json``
means the same thing here; live-only keys (timing, faults, nodes, sizes) are
added beside them.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from .io import messages as msg
from .simulate import json_clean as _clean
from .stats import percentiles

ROLES = ("plant", "encoder", "attacker", "controller")
PT = msg.PlantTelemetry
CT = msg.ControllerTelemetry


def _nan(n: int) -> np.ndarray:
    return np.full(n, np.nan)


def _agree_where_known(xi_e, E_e, xi_d, E_d) -> bool:
    """xi_k, E_k identical at both ends on every sample where both were recorded."""
    known = np.isfinite(E_e) & np.isfinite(E_d)
    return bool(np.array_equal(xi_e[known], xi_d[known]) and np.array_equal(E_e[known], E_d[known]))


@dataclass
class RunData:
    """What a run left behind: per-sample telemetry by node and k, events, attacker status, node summaries."""

    tele: dict[str, dict[int, object]]
    plant_final: msg.PlantTelemetry | None = None
    events: list = field(default_factory=list)
    status: list = field(default_factory=list)
    summaries: dict[str, dict] = field(default_factory=dict)


def build_summary(sc, data: RunData, *, run_id: str, ack_via_attacker: bool, nodes: dict, faults: list,
                  codebook) -> dict:
    """One JSON-able dict: ``testbed simulate --json`` keys plus timing, faults and node reports."""
    from .flow import FLOW_OK
    from .simulate import SimResult, summarize

    plant = sc.make_model()
    n, m = plant.n, plant.m
    Tn = int(round(sc.T * 1e9))
    P = data.tele.get("plant", {})
    EN = data.tele.get("encoder", {})
    C = data.tele.get("controller", {})
    A = data.tele.get("attacker", {})
    final = data.plant_final
    events = data.events
    status = data.status
    summaries = data.summaries
    if final is not None:
        N = final.k
    else:
        N = max(P) + 1 if P else 0
    x = np.full((N, n), np.nan)
    u = np.zeros((N, m))
    q = np.full((N, n), np.nan)
    q_enc = np.full((N, n), np.nan)
    xi_enc = np.full((N, n), np.nan)
    xi_dec = np.full((N, n), np.nan)
    E_enc, E_dec = _nan(N), _nan(N)
    theta = np.ones(N, dtype=np.uint8)
    symbols = np.full(N, -1, dtype=np.int64)
    sat = np.zeros(N, dtype=bool)
    jitter, s2a, misses, overruns, no_u = [], [], 0, 0, 0
    st_enc, st_proxy, st_ctl, st_plant = [], [], [], []
    d_ns = int(sc.run.deadline * Tn)
    reasons = Counter()
    for k in range(N):
        p = P.get(k)
        if p is not None:
            x[k] = p.x
            u[k] = p.u
            jitter.append(p.t_ns - k * Tn)
            if p.t_ns - k * Tn > d_ns:
                overruns += 1
            if p.u_rx_ns != msg.NO_TIME and p.theta == 0:  # u_k computed from the symbol of x_k
                s2a.append(p.u_rx_ns - p.t_ns)
            if p.flags & PT.FLAG_MISS:
                misses += 1
            if p.flags & PT.FLAG_NO_U:
                no_u += 1
        e = EN.get(k)
        if e is not None and not e.silent:
            symbols[k] = e.symbol
            sat[k] = bool(e.saturated)
            xi_enc[k] = e.xi
            E_enc[k] = e.E
            q_enc[k] = e.q
            if p is not None:
                st_enc.append(e.tx_ns - p.t_ns)
        c = C.get(k)
        if c is not None:
            theta[k] = c.theta
            q[k] = c.q
            xi_dec[k] = c.xi
            E_dec[k] = c.E
            reasons[c.reason] += 1
            if p is not None and p.u_rx_ns != msg.NO_TIME:
                st_plant.append(p.u_rx_ns - c.tx_ns)
        elif p is not None and p.theta != msg.THETA_NONE:
            theta[k] = p.theta
        a = A.get(k)
        if a is not None and a.tx_ns != msg.NO_TIME:
            if e is not None and e.tx_ns != msg.NO_TIME:
                st_proxy.append(a.tx_ns - e.tx_ns)
            if c is not None and c.reason == CT.RECEIVED:
                st_ctl.append(c.tx_ns - a.tx_ns)
    if final is not None:
        x_final = np.array(final.x)
        flow_status = final.flow_status
    else:
        x_final = x[-1] if N else np.array(sc.x0, dtype=float)
        flow_status = FLOW_OK
    diverged_at = -1
    for k in range(N):
        if P.get(k) is not None and P[k].flow_status != FLOW_OK:
            diverged_at = k
            break
    res = SimResult(T=sc.T, t=np.arange(N) * sc.T, x=x, u=u, q=q, q_enc=q_enc, xi_enc=xi_enc, E_enc=E_enc,
                    xi_dec=xi_dec, E_dec=E_dec, theta=theta, symbols=symbols, saturated=sat, x_final=x_final,
                    flow_status=int(flow_status), diverged_at=diverged_at, K=np.asarray(sc.K, dtype=float))
    pf = next((e for e in events if e.node == "plant" and e.kind == "plant_fault"), None)
    if pf is not None:  # the true plant failed (an FMU step): the run ended at that sample
        res.plant_fault, res.plant_fault_at = pf.detail, int(pf.k)
    if not np.all(np.isfinite(x_final)):
        res.x_final = np.array(sc.x0, dtype=float)
        out = summarize(sc, res)
        out.update(x_final=None, final_norm=None, converged=False, escaped=None)
    else:
        out = summarize(sc, res)
    out = _clean(out)
    base_keys = set(out)
    ps = summaries.get("plant", {})
    es = summaries.get("encoder", {})
    cs = summaries.get("controller", {})
    ats = summaries.get("attacker", {})
    ev_count = Counter(e.kind for e in events)
    out.update({
        "live": True,
        "run_id": run_id,
        "timing_mode": sc.run.timing,
        "deadline": sc.run.deadline,
        "ack_via_attacker": bool(ack_via_attacker),
        "samples": N,
        "n_steps": sc.n_steps,
        "complete": final is not None and N == sc.n_steps,
        "t_sample": [None if P.get(k) is None else P[k].t_ns / 1e9 for k in range(N)],
        "u_controller": [None if C.get(k) is None else list(C[k].u) for k in range(N)],
        "xi_dec": xi_dec.tolist(),
        "encoder_decoder_agree_where_known": _agree_where_known(xi_enc, E_enc, xi_dec, E_dec),
        "deadline_missed_at": [k for k in range(N) if P.get(k) is not None and P[k].flags & PT.FLAG_MISS],
        "withheld_at": [k for k in range(N) if EN.get(k) is not None and EN[k].silent],
        "attacker_dropped_at": [k for k in range(N) if A.get(k) is not None and A[k].dropped],
        "loss_reasons": {"received": reasons[CT.RECEIVED], "deadline": reasons[CT.DEADLINE],
                         "invalid": reasons[CT.INVALID], "superseded": reasons[CT.SUPERSEDED]},
        "invalid_payloads": cs.get("invalid", reasons[CT.INVALID]),
        "late_symbols": cs.get("late"),
        "malformed": {r: summaries.get(r, {}).get("malformed") for r in ROLES},
        "controller_lost_at": ps.get("controller_lost_at", -1),
        "sizes": {"symbol_payload_bytes": codebook.nbytes, "symbol_bits": codebook.bits,
                  "header_bytes": msg.HEADER_SIZE, "sensor_payload_bytes": 8 * n,
                  "actuation_payload_bytes": 5 + 8 * m, "ack_payload_bytes": 5,
                  "header_overhead_per_symbol": msg.HEADER_SIZE / codebook.nbytes},
        "timing": {
            "T_us": Tn / 1e3,
            "sampling_jitter_us": percentiles(jitter),
            "sensor_to_actuator_us": percentiles(s2a),
            "stages_us": {"encoder": percentiles(st_enc), "proxy": percentiles(st_proxy),
                          "controller": percentiles(st_ctl), "plant": percentiles(st_plant)},
            "deadline_misses": misses,
            "u_missing": no_u,
            "overruns": overruns,
            "ack_rtt_us": es.get("ack_rtt_us"),
        },
        "events": dict(ev_count),
        "event_log": [dict(node=e.node, kind=e.kind, k=e.k, detail=e.detail) for e in events[:50]],
        "attacker_status": [dict(k=s.k, attack_on=s.attack_on, dropped=s.dropped) for s in status],
        "faults": faults,
        "nodes": nodes,
        "node_summaries": summaries,
    })
    out["attacker"] = {"dropped": ats.get("dropped"), "forwarded": ats.get("forwarded"),
                       "corrupted": ats.get("corrupted"), "acks_dropped": ats.get("acks_dropped")}
    return {k: v if k in base_keys else _clean(v) for k, v in out.items()}
