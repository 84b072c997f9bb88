"""The launcher's collector: subscribes to a run's telemetry and builds its summary.

Everything arrives over Zenoh as it happens, so a node killed mid-run leaves
its telemetry up to the kill.  ``build_summary`` assembles the per-sample
arrays into a ``SimResult`` and reuses ``testbed.simulate.summarize``, so the
keys of ``testbed run --json`` mean what they mean in ``testbed simulate --json``;
live-only keys (timing, faults, nodes, sizes) are added beside them.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter

import numpy as np

from ..io import messages as msg
from ..io import transport
from .common import T_ns, percentiles

PT = msg.PlantTelemetry
CT = msg.ControllerTelemetry


class Collector:
    """Telemetry, events, node summaries, start/stop and liveliness of one run."""

    def __init__(self, session, keys: transport.Keys):
        import zenoh

        self._zenoh = zenoh
        self.keys = keys
        self.lock = threading.Lock()
        self.tele: dict[str, dict[int, object]] = {r: {} for r in transport.ROLES}
        self.plant_final: msg.PlantTelemetry | None = None
        self.events: list[msg.Event] = []
        self.summaries: dict[str, dict] = {}
        self.status: list[msg.AttackerStatus] = []
        self.start: msg.Start | None = None
        self.start_rx_mono = 0
        self.stops: list[msg.Stop] = []
        self.liveliness: list[tuple[int, str, bool]] = []  # (monotonic ns, node, alive)
        self.alive: set[str] = set()
        self.bad = 0
        p = keys.prefix
        self._subs = [
            session.declare_subscriber(f"{p}/telemetry/*", self._on_telemetry),
            session.declare_subscriber(f"{p}/events/*", self._on_event),
            session.declare_subscriber(f"{p}/summary/*", self._on_summary),
            session.declare_subscriber(keys.attacker_status, self._on_status),
            session.declare_subscriber(keys.start, self._on_start),
            session.declare_subscriber(keys.stop, self._on_stop),
            session.liveliness().declare_subscriber(keys.alive("*"), self._on_alive, history=True),
        ]

    def _on_telemetry(self, sample) -> None:
        role = transport.Keys.node_of(sample.key_expr)
        typ = msg.TELEMETRY_TYPES.get(role)
        if typ is None:
            return
        try:
            recs = [typ.decode(r) for r in msg.unpack_batch(sample.payload)]
        except msg.MessageError:
            self.bad += 1
            return
        with self.lock:
            for t in recs:
                if role == "plant" and t.flags & PT.FLAG_FINAL:
                    self.plant_final = t
                else:
                    self.tele[role][t.k] = t

    def _on_event(self, sample) -> None:
        try:
            e = msg.Event.decode(sample.payload)
        except msg.MessageError:
            self.bad += 1
            return
        with self.lock:
            self.events.append(e)

    def _on_summary(self, sample) -> None:
        try:
            s = msg.NodeSummary.decode(sample.payload)
        except msg.MessageError:
            self.bad += 1
            return
        with self.lock:
            self.summaries[s.node] = s.data

    def _on_status(self, sample) -> None:
        try:
            s = msg.AttackerStatus.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            self.status.append(s)

    def _on_start(self, sample) -> None:
        try:
            s = msg.Start.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            if self.start is None:
                self.start = s
                self.start_rx_mono = time.monotonic_ns()

    def _on_stop(self, sample) -> None:
        try:
            s = msg.Stop.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            self.stops.append(s)

    def _on_alive(self, sample) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        alive = sample.kind != self._zenoh.SampleKind.DELETE
        with self.lock:
            self.liveliness.append((time.monotonic_ns(), node, alive))
            (self.alive.add if alive else self.alive.discard)(node)

    # ---- queries
    def last_k(self, role: str) -> int:
        with self.lock:
            d = self.tele.get(role, {})
            return max(d) if d else -1

    def lost_at(self, node: str) -> int | None:
        """monotonic ns at which ``node``'s liveliness token went away (last time), or None."""
        with self.lock:
            for t, n, alive in reversed(self.liveliness):
                if n == node:
                    return None if alive else t
        return None

    def plant_done(self) -> bool:
        with self.lock:
            return any(s.origin == "plant" for s in self.stops)


# ============================================================================ summary
def _nan(n: int) -> np.ndarray:
    return np.full(n, np.nan)


def _clean(o):
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, list):
        return [_clean(v) for v in o]
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    return o


def _agree_where_known(xi_e, E_e, xi_d, E_d) -> bool:
    """xi_k, E_k identical at both ends on every sample where both were recorded."""
    known = np.isfinite(E_e) & np.isfinite(E_d)
    return bool(np.array_equal(xi_e[known], xi_d[known]) and np.array_equal(E_e[known], E_d[known]))


def build_summary(sc, col: Collector, *, run_id: str, opts, nodes: dict, faults: list, codebook) -> dict:
    """One JSON-able dict: ``testbed simulate --json`` keys plus timing, faults and node reports."""
    from ..flow import FLOW_OK
    from ..simulate import SimResult, summarize

    plant = sc.make_plant()
    n, m = plant.n, plant.m
    Tn = T_ns(sc)
    with col.lock:
        P = dict(col.tele["plant"])
        EN = dict(col.tele["encoder"])
        C = dict(col.tele["controller"])
        A = dict(col.tele["attacker"])
        final = col.plant_final
        events = list(col.events)
        status = list(col.status)
        summaries = dict(col.summaries)
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
    if not np.all(np.isfinite(x_final)):
        res.x_final = np.array(sc.x0, dtype=float)
        out = summarize(sc, res)
        out.update(x_final=None, final_norm=None, converged=False, escaped=None)
    else:
        out = summarize(sc, res)
    out = _clean(out)
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
        "ack_via_attacker": bool(opts.ack_via_attacker),
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
        "malformed": {r: summaries.get(r, {}).get("malformed") for r in transport.ROLES},
        "controller_lost_at": ps.get("controller_lost_at", -1),
        "sizes": {"symbol_payload_bytes": codebook.nbytes, "symbol_bits": codebook.bits,
                  "header_bytes": msg.HEADER_SIZE, "sensor_payload_bytes": 8 * n,
                  "actuation_payload_bytes": 1 + 8 * m, "ack_payload_bytes": 5,
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
    return _clean(out)
