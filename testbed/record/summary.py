"""Assemble a run's summary from its per-sample telemetry: shared by ``testbed run`` and ``testbed report``.

Both feed it columns (``testbed.record.columns.Columns``): the live launcher what
its collector received over Zenoh, ``testbed report`` what a recording holds,
so both print the same keys.  The
per-sample arrays become a ``SimResult`` and go through
``testbed.sim.batch.summarize``, so every key of ``testbed simulate --json``
means the same thing here; live-only keys (timing, faults, nodes, sizes) are
added beside them.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from ..loop.channel import loss_tally, losses_of_tally, model_lost
from ..sim.batch import json_clean as _clean
from ..sim.loop import equal_where
from ..wire import messages as msg
from ..wire import transport
from .degraded import timing_degraded
from .timingstats import Spool, StoredArray, percentiles

if TYPE_CHECKING:
    from concurrent.futures import Future

    from ..loop.params import Codebook
    from ..scenario import Scenario
    from .columns import Columns

PT = msg.PlantTelemetry
CT = msg.ControllerTelemetry



def _agree_where_known(xi_e: np.ndarray, E_e: np.ndarray, xi_d: np.ndarray, E_d: np.ndarray) -> bool:
    """xi_k, E_k identical at both ends on every sample where both were recorded."""
    known = np.isfinite(E_e) & np.isfinite(E_d)
    return equal_where(xi_e, xi_d, known) and equal_where(E_e, E_d, known)


class RowsOrNone:
    """Per-sample vectors where a missing sample is ``null`` as a whole (not a row of nulls) in JSON."""

    def __init__(self, values: np.ndarray | StoredArray, mask: np.ndarray | StoredArray) -> None:
        self.values, self.mask = values, mask

    def tolist(self) -> list:
        return [row if ok else None for row, ok in zip(self.values.tolist(), self.mask.tolist())]


#: the telemetry fields ``build_summary`` prints (``testbed.record.columns.read_columns(fields=...)``); q_k at the
#: encoder is not printed and stays NaN unless decoded (``testbed.open`` decodes every field)
SUMMARY_FIELDS = {
    "plant.x", "plant.x_meas", "plant.u", "plant.t_ns", "plant.u_rx_ns", "plant.theta", "plant.flags", "plant.flow_status",
    "encoder.symbol", "encoder.saturated", "encoder.silent", "encoder.E", "encoder.xi", "encoder.tx_ns",
    "controller.theta", "controller.q", "controller.xi", "controller.E", "controller.reason", "controller.tx_ns",
    "controller.u",
    "attacker.tx_ns", "attacker.dropped", "attacker.attack_on",
}


#: samples of the timing section's differences computed at a time (their percentiles: ``stats.Spool``)
TIMING_WINDOW = 1 << 16


def _diffs(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """a - b (ns) where ``mask`` and both times happened."""
    ok = mask & (a != msg.NO_TIME) & (b != msg.NO_TIME)
    return a[ok] - b[ok]


def lockstep_checked(sc: Scenario) -> bool:
    """Whether a run's method declares a shared state of its two ends (``EncoderEnd.state``, by default xi and
    E; the paper's ends are checked by ``encoder_decoder_agree``): only then are breaks of lockstep counted."""
    try:
        model = sc.make_model()
        end = sc.make_method().make_decoder(model, sc.K, sc.quantizer, sc.flow)
    except Exception:  # noqa: BLE001 - a method that cannot build its end: its run says why elsewhere
        return False
    return getattr(end, "state", None) is not None


def lockstep_breaks_in(xi_enc: np.ndarray, E_enc: np.ndarray, xi_dec: np.ndarray, E_dec: np.ndarray,
                      both: np.ndarray) -> np.ndarray:
    """The samples (indices into the arrays) where the ends' recorded xi_k and E_k differ, of those ``both``
    recorded with a symbol sent (a method whose ends share a state: ``lockstep_checked``)."""
    both = both & np.isfinite(E_enc) & np.isfinite(E_dec)
    return np.flatnonzero(both & ((E_enc != E_dec) | np.any(xi_enc != xi_dec, axis=1)))


def late_for_schedule(sc: Scenario, arrival_ns: np.ndarray) -> int:
    """Physical timing, scheduled actuation: how many received u_k arrived (``arrival_ns`` after
    t_k) later than their scheduled instant; 0 otherwise."""
    tp = sc.timing_params
    return int(np.count_nonzero(arrival_ns > int(tp[2]))) if (tp[0] and tp[1]) else 0


def column_rows(cols: Columns, a: int, b: int) -> Columns:
    """Rows a .. b - 1 of ``cols`` as columns of their own (views: nothing copied)."""
    from dataclasses import replace

    return replace(cols, tables={t: v[a:b] for t, v in cols.tables.items()}, present=cols.present[a:b],
                   rows=max(0, b - a))


class ColumnChunks:
    """A run's whole columns (``Columns``) handed to ``build_summary`` a chunk of rows at a time, as the
    launcher's spill is (``testbed.live.collect.SpillRows``): the same interface, for the tests of chunking."""

    def __init__(self, cols: Columns, size: int | None = None) -> None:
        self.cols, self.size = cols, size

    def __getattr__(self, name: str) -> Any:
        return getattr(self.cols, name)

    def chunks(self, hi: int) -> Iterator[tuple[int, Columns]]:
        """``(k0, columns of rows k0 ..)`` covering rows 0 .. hi - 1 (at least one chunk, maybe empty)."""
        size = max(1, int(self.size or hi or 1))
        for a in range(0, max(hi, 1), size):
            yield a, column_rows(self.cols, a, min(hi, a + size))


def build_summary(sc: Scenario, cols: Any, *, run_id: str, ack_via_attacker: bool, nodes: dict, faults: list,
                  codebook: Codebook, arrays: bool = False, store: str | Path | None = None) -> dict:
    """One JSON-able dict: ``testbed simulate --json`` keys plus timing, faults and node reports.

    ``cols``: a ``testbed.record.columns.Columns`` (a recording, or the live collector's
    snapshot), or rows a chunk at a time (``ColumnChunks``; the launcher's ``collect.SpillRows``): every
    reduction is made chunk by chunk (``sim.batch.RunTally``, ``channel.loss_tally``, ``stats.Spool``), so the
    summary is the same however the rows are cut.  ``arrays``: per-sample values stay numpy arrays
    (``write_json`` streams them); otherwise plain lists.  ``store``: a folder where they are kept in files
    (``stats.Stack``: ``StoredArray`` values) rather than in memory (None).
    """
    from ..loop.flow import FLOW_OK
    from ..sim.batch import MemStack, RunTally
    from ..sim.loop import Replay, SimResult
    from .timingstats import Stack

    # ``Columns``, ``ColumnChunks`` or the launcher's ``SpillRows``: the columns' attributes, read alike
    src: Any = cols if hasattr(cols, "chunks") else ColumnChunks(cols)
    plant = sc.make_model()
    n, m = plant.n, plant.m
    Tn = int(round(sc.T * 1e9))
    final = src.final
    N = final["k"] if final is not None else src.last_k("plant") + 1
    N = max(0, min(N, src.rows))
    events = src.events
    # a method's end raised at sample k (its node's event): the run ended there, as testbed simulate ends it
    mf = next((e for e in events if e.kind == "method_fault" and e.k >= 0), None)
    if mf is not None and mf.k > N:
        mf = None  # the plant's record ended before it (it died): that fault is the one to report
    x_fault = None
    if mf is not None:
        N = int(mf.k)
    stack: Callable[[], MemStack | Stack] = MemStack if store is None else (lambda: Stack(store))
    tally = RunTally(sc.T, stack)
    st = {k: stack() for k in ("t_sample", "u_ctl", "u_mask", "xi_dec", "missed", "withheld", "dropped")}
    # the timing section's ns differences go to files a window of samples at a time (``stats.Spool``: exact
    # percentiles in bounded memory)
    spools = {name: Spool() for name in ("jitter", "s2a", "encoder", "plant", "proxy", "controller")}
    d_ns = int(sc.run.deadline * Tn)
    overruns = late_sched = misses = no_u = 0
    n_reason = np.zeros(4, dtype=np.int64)
    diverged_at = -1
    agree_known = True
    xm_col = ("plant", "x_meas") in src.lay.cols
    xm_seen = False
    x_last = None
    K = np.asarray(sc.K, dtype=float)
    checked = lockstep_checked(sc)
    net = getattr(sc, "network", None)
    ch_lost = model_lost(net, N) if net is not None else None
    losses = np.zeros(5, dtype=np.int64)
    for a, c in src.chunks(min(src.rows, N + 1) if mf is not None else N):
        g = c.get
        if mf is not None and a <= N < a + c.rows and c.has("plant")[N - a]:
            x_fault = g("plant", "x")[N - a].copy()  # x_k at the method's fault
        R = max(0, min(c.rows, N - a))
        if R == 0 and a > 0:
            continue
        P, EN, C, A = (c.has(r)[:R] for r in ("plant", "encoder", "controller", "attacker"))
        silent = g("encoder", "silent")[:R] != 0
        E_ok = EN & ~silent
        # the columns hold NaN (u: 0, symbol: -1) where a sample was not recorded or its symbol withheld
        x, u = g("plant", "x")[:R], g("plant", "u")[:R]
        xi_enc, E_enc = g("encoder", "xi")[:R], g("encoder", "E")[:R]
        xi_dec, E_dec = g("controller", "xi")[:R], g("controller", "E")[:R]
        p_theta = g("plant", "theta")[:R]
        theta = np.ones(R, dtype=np.uint8)
        from_plant = ~C & P & (p_theta != msg.THETA_NONE)
        theta[from_plant] = p_theta[from_plant]
        theta[C] = g("controller", "theta")[:R][C]
        t_ns, u_rx, flags = g("plant", "t_ns")[:R], g("plant", "u_rx_ns")[:R], g("plant", "flags")[:R]
        e_tx, c_tx, a_tx = g("encoder", "tx_ns")[:R], g("controller", "tx_ns")[:R], g("attacker", "tx_ns")[:R]
        reason = g("controller", "reason")[:R]
        has_t = P & (t_ns != msg.NO_TIME)
        for w0 in range(0, R, TIMING_WINDOW):
            w = slice(w0, min(R, w0 + TIMING_WINDOW))
            jitter = t_ns[w][has_t[w]] - (np.flatnonzero(has_t[w]) + a + w0) * Tn
            overruns += int(np.count_nonzero(jitter > d_ns))
            s2a = _diffs(u_rx[w], t_ns[w], P[w] & (p_theta[w] == 0))
            late_sched += late_for_schedule(sc, s2a)
            for name, v in (("jitter", jitter), ("s2a", s2a),
                            ("encoder", _diffs(e_tx[w], t_ns[w], E_ok[w] & P[w])),
                            ("plant", _diffs(u_rx[w], c_tx[w], C[w] & P[w])),
                            ("proxy", _diffs(a_tx[w], e_tx[w], A[w] & EN[w])),
                            ("controller", _diffs(c_tx[w], a_tx[w], A[w] & C[w] & (reason[w] == CT.RECEIVED)))):
                spools[name].extend(v)
        missed = P & (flags & PT.FLAG_MISS != 0)
        misses += int(np.count_nonzero(missed))
        no_u += int(np.count_nonzero(P & (flags & PT.FLAG_NO_U != 0)))
        if R:
            n_reason += np.bincount(reason[C], minlength=4)[:4]
            x_last = x[-1].copy()
        bad_flow = np.flatnonzero(P & (g("plant", "flow_status")[:R] != FLOW_OK))
        if diverged_at < 0 and bad_flow.size:
            diverged_at = int(bad_flow[0]) + a
        xm = g("plant", "x_meas")[:R] if xm_col else None  # what the sensor read ([plant.sensor]); NaN where not
        xm_seen = xm_seen or (xm is not None and bool(np.isfinite(xm).any()))
        dropped = A & (g("attacker", "dropped")[:R] != 0)
        withheld = EN & silent
        chunk = SimResult(T=sc.T, t=np.arange(a, a + R) * sc.T, x=x, u=u, q=g("controller", "q")[:R],
                          q_enc=g("encoder", "q")[:R], xi_enc=xi_enc, E_enc=E_enc, xi_dec=xi_dec, E_dec=E_dec,
                          theta=theta, symbols=g("encoder", "symbol")[:R],
                          saturated=E_ok & (g("encoder", "saturated")[:R] != 0), x_final=x[:0], K=K, x_meas=xm)
        if checked:
            chunk.lockstep_breaks = lockstep_breaks_in(xi_enc, E_enc, xi_dec, E_dec, E_ok & C) + a
        tally.add(a, chunk)
        agree_known = agree_known and _agree_where_known(xi_enc, E_enc, xi_dec, E_dec)
        for key, v in (("t_sample", np.where(has_t, t_ns / 1e9, np.nan)), ("u_ctl", g("controller", "u")[:R]),
                       ("u_mask", C), ("xi_dec", xi_dec), ("missed", np.flatnonzero(missed) + a),
                       ("withheld", np.flatnonzero(withheld) + a), ("dropped", np.flatnonzero(dropped) + a)):
            st[key].append(v)
        losses += loss_tally(theta, withheld=withheld, attacker=dropped, invalid=C & (reason == CT.INVALID),
                             superseded=C & (reason == CT.SUPERSEDED),
                             channel_lost=None if ch_lost is None else ch_lost[a:a + R])
    timing = {name: percentiles(sp) for name, sp in spools.items()}
    for sp in spools.values():
        sp.close()
    if x_fault is not None:  # x_k at the method's fault (the plant may have run on until the Stop)
        x_final, flow_status = x_fault, FLOW_OK
    elif final is not None:
        x_final = np.array(final["x"], dtype=float)
        flow_status = final["flow_status"]
    else:
        x_final = x_last if N else np.array(sc.x0, dtype=float)
        flow_status = FLOW_OK
    none = np.zeros((0,))
    res = SimResult(T=sc.T, t=none, x=np.zeros((0, n)), u=none, q=none, q_enc=none, xi_enc=none, E_enc=none,
                    xi_dec=none, E_dec=none, theta=none, symbols=none, saturated=none, x_final=x_final,
                    flow_status=int(flow_status), diverged_at=diverged_at, K=K,
                    simulator=src.metadata.get("testbed.run", {}).get("simulator"))  # None: a live run
    if mf is not None:
        res.method_fault, res.method_fault_at = mf.detail, int(mf.k)
    pf = next((e for e in events if e.node == "plant" and e.kind == "plant_fault"), None)
    if pf is not None:  # the true plant failed (an FMU step): the run ended at that sample
        res.plant_fault, res.plant_fault_at = pf.detail, int(pf.k)
    use_xm = xm_col and xm_seen

    def record() -> Iterator[tuple[int, np.ndarray, Replay]]:
        """What the ends saw, as ``testbed resimulate`` replays it: the escape verdict rebuilds the ends from it."""
        for a, c in src.chunks(N):
            R = max(0, min(c.rows, N - a))
            C, EN = c.has("controller")[:R], c.has("encoder")[:R]
            silent = c.get("encoder", "silent")[:R] != 0
            X = c.get("plant", "x_meas" if use_xm else "x")[:R]
            yield a, X, Replay(reason=np.where(C, c.get("controller", "reason")[:R], -1).astype(np.int64),
                               sensed=EN.copy(), withheld=EN & silent, u_missing=np.zeros(R, dtype=bool))

    if not np.all(np.isfinite(x_final)):
        res.x_final = np.array(sc.x0, dtype=float)
        out = tally.summarize(sc, res, arrays=arrays, record=record, x_meas=use_xm)
        out.update(x_final=None, final_norm=None, converged=False, escaped=None)
    else:
        out = tally.summarize(sc, res, arrays=arrays, record=record, x_meas=use_xm)
    out = _clean(out)
    base_keys = set(out)
    summaries = src.summaries
    ps = summaries.get("plant", {})
    es = summaries.get("encoder", {})
    cs = summaries.get("controller", {})
    ats = summaries.get("attacker", {})
    ev_count = Counter(e.kind for e in events)
    L = (lambda a: a) if arrays else (lambda a: a.tolist())
    t_sample = st["t_sample"].result()
    xi_dec = st["xi_dec"].result()
    u_ctl = RowsOrNone(st["u_ctl"].result(), st["u_mask"].result())
    out.update({
        "live": True,
        "run_id": run_id,
        "timing_mode": sc.run.timing,
        "deadline": sc.run.deadline,
        "ack_via_attacker": bool(ack_via_attacker),
        "samples": N,
        "n_steps": sc.n_steps,
        "complete": final is not None and N == sc.n_steps,
        "t_sample": t_sample if arrays else _clean(t_sample.tolist()),
        "u_controller": u_ctl if arrays else _clean(u_ctl.tolist()),
        "xi_dec": xi_dec if arrays else _clean(xi_dec.tolist()),
        "encoder_decoder_agree_where_known": agree_known,
        "deadline_missed_at": L(st["missed"].result()),
        "withheld_at": L(st["withheld"].result()),
        "attacker_dropped_at": L(st["dropped"].result()),
        "loss_reasons": {"received": int(n_reason[CT.RECEIVED]), "deadline": int(n_reason[CT.DEADLINE]),
                         "invalid": int(n_reason[CT.INVALID]), "superseded": int(n_reason[CT.SUPERSEDED])},
        "invalid_payloads": cs.get("invalid", int(n_reason[CT.INVALID])),
        "late_symbols": cs.get("late"),
        "malformed": {r: summaries.get(r, {}).get("malformed") for r in transport.ROLES},
        "controller_lost_at": ps.get("controller_lost_at", -1),
        "sizes": {"symbol_payload_bytes": codebook.nbytes, "symbol_bits": codebook.bits,
                  "header_bytes": msg.HEADER_SIZE, "sensor_payload_bytes": 8 * n,
                  "actuation_payload_bytes": 5 + 8 * m, "ack_payload_bytes": 5,
                  "header_overhead_per_symbol": msg.HEADER_SIZE / codebook.nbytes if codebook.nbytes else None},
        "timing": {
            "T_us": Tn / 1e3,
            "sampling_jitter_us": timing["jitter"],
            "sensor_to_actuator_us": timing["s2a"],
            "stages_us": {"encoder": timing["encoder"], "proxy": timing["proxy"],
                          "controller": timing["controller"], "plant": timing["plant"]},
            "deadline_misses": misses,
            "u_missing": no_u,
            "overruns": overruns,
            "late_for_schedule": late_sched,
            "ack_rtt_us": es.get("ack_rtt_us"),
        },
        "events": dict(ev_count),
        "event_log": [dict(node=e.node, kind=e.kind, k=e.k, detail=e.detail) for e in events[:50]],
        "attacker_status": [dict(k=s.k, attack_on=s.attack_on, dropped=s.dropped) for s in src.status],
        "faults": faults,
        "nodes": nodes,
        "node_summaries": summaries,
    })
    # one cause per lost sample (channel.LOSS_KINDS; docs/recording-format.md)
    out["losses"] = losses_of_tally(losses, cs.get("late"))
    out["attacker"] = {"dropped": ats.get("dropped"), "forwarded": ats.get("forwarded"),
                       "corrupted": ats.get("corrupted"), "acks_dropped": ats.get("acks_dropped")}
    out.update(timing_degraded(out))  # by the criterion of ``testbed.record.degraded``
    return {k: v if k in base_keys else _clean(v) for k, v in out.items()}


# ============================================================================ JSON out, streamed
_BLOCK = 1 << 14


_POOL = None
_ARROW_TYPES = {"f8": "float64", "i8": "int64", "i4": "int32", "i2": "int16", "i1": "int8", "u8": "uint64",
                "u4": "uint32", "u2": "uint16", "u1": "uint8"}


def arrow_array(col: np.ndarray) -> Any:
    """A 1-D numpy array as an Arrow array over its buffer (``pa.array`` imports pandas, 40 MB, on first
    use); a dtype Arrow has no plain type for is cast to float64 (``arrow_plain`` says which have one)."""
    import pyarrow as pa

    global _POOL
    if _POOL is None:  # the system allocator gives freed blocks back; the default pools keep them
        _POOL = pa.system_memory_pool()
        pa.set_memory_pool(_POOL)

    col = np.ascontiguousarray(col)
    if col.dtype == bool:
        return pa.Array.from_buffers(pa.bool_(), len(col), [None, pa.py_buffer(np.packbits(col, bitorder="little"))])
    key = f"{col.dtype.kind}{col.dtype.itemsize}"
    if key not in _ARROW_TYPES:
        col, key = col.astype(np.float64), "f8"
    return pa.Array.from_buffers(getattr(pa, _ARROW_TYPES[key])(), len(col), [None, pa.py_buffer(col)])


def arrow_plain(col: np.ndarray) -> bool:
    """Whether ``arrow_array`` keeps ``col``'s dtype (booleans, integers and float64)."""
    return col.dtype == bool or f"{col.dtype.kind}{col.dtype.itemsize}" in _ARROW_TYPES


def _lit(text: str) -> Any:
    """A string literal for ``pyarrow.compute`` as an Arrow scalar made over a buffer: a Python ``str`` argument
    is converted by ``pa.scalar``, which imports pandas (40 MB)."""
    import pyarrow as pa

    b = text.encode()
    return pa.Array.from_buffers(pa.string(), 1, [None, pa.py_buffer(np.array([0, len(b)], dtype=np.int32)),
                                                  pa.py_buffer(b)])[0]


def _texts(col: np.ndarray) -> Any:
    """A 1-D array as JSON texts, one per value (Arrow's shortest round-trip formatting, vectorized).

    Floats parse back to the same double as ``json.dumps`` writes (an integral
    float keeps its ``.0``); NaN and infinities are ``null`` as ``_clean`` makes them.
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    s = pc.cast(arrow_array(col), pa.string())
    if col.dtype.kind == "f":
        fin = np.isfinite(col)
        # only an integral value can print without "." or "e": the texts of those alone are looked at
        integral = fin & (np.floor(col) == col)
        if integral.any():
            sub = pc.take(s, arrow_array(np.flatnonzero(integral)))
            plain = pc.invert(pc.or_(pc.match_substring(sub, "."), pc.match_substring(sub, "e")))
            sub = pc.if_else(plain, pc.binary_join_element_wise(sub, _lit(".0"), _lit("")), sub)
            s = pc.replace_with_mask(s, arrow_array(integral), sub)
        if not fin.all():
            s = pc.if_else(arrow_array(fin), s, _lit("null"))
    return s


def _joined(s: Any) -> str:
    """The texts of a string array joined by ", " (read straight from Arrow's value buffer)."""
    import pyarrow.compute as pc

    if len(s) == 0:
        return ""
    s = pc.binary_join_element_wise(s, _lit(", "), _lit(""))
    offsets = np.frombuffer(s.buffers()[1], dtype=np.int32)
    lo, hi = int(offsets[s.offset]), int(offsets[s.offset + len(s)])
    return memoryview(s.buffers()[2])[lo:hi - 2].tobytes().decode("ascii")


def _row_texts(b: np.ndarray, mask: np.ndarray | None = None) -> Any:
    """Rows of a block as texts: scalars, ``[a, b]`` for vectors; ``null`` where ``mask`` is False."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if b.ndim == 1:
        s = _texts(b)
    elif b.shape[1] == 0:
        zeros = pc.cast(arrow_array(np.zeros(len(b), np.int8)), pa.string())
        s = pc.binary_join_element_wise(zeros, _lit("[]"), _lit(""))
        s = pc.utf8_slice_codeunits(s, 1)
    else:
        inner = pc.binary_join_element_wise(*[_texts(np.ascontiguousarray(b[:, j])) for j in range(b.shape[1])],
                                            _lit(", "))
        s = pc.binary_join_element_wise(_lit("["), inner, _lit("]"), _lit(""))
    if mask is not None:
        s = pc.if_else(arrow_array(np.asarray(mask, dtype=bool)), s, _lit("null"))
    return s


def _json_array(a: np.ndarray | StoredArray, w: Callable[[str], object],
                mask: np.ndarray | StoredArray | None = None) -> None:
    """A per-sample array as the JSON of ``_clean(a.tolist())``, a block of rows at a time.

    Blocks are formatted on two threads (Arrow releases the GIL), at most two ahead of the writer.
    """
    from concurrent.futures import ThreadPoolExecutor

    def text(i: int) -> str:
        return _joined(_row_texts(a[i:i + _BLOCK], None if mask is None else mask[i:i + _BLOCK]))

    w("[")
    starts = list(range(0, len(a), _BLOCK))
    if len(starts) <= 1:
        if starts:
            w(text(0))
    else:
        with ThreadPoolExecutor(2) as ex:
            todo = deque(starts)
            inflight: deque[Future[str]] = deque()
            while todo or inflight:
                while todo and len(inflight) < 2:
                    inflight.append(ex.submit(text, todo.popleft()))
                t = inflight.popleft().result()
                w(t)
                if inflight or todo:
                    w(", ")
    w("]")


def write_json(obj: Any, fp: IO[str]) -> None:
    """``json.dump(obj, fp)`` for summaries holding numpy arrays, without building their lists at once."""
    import json

    w = fp.write
    if isinstance(obj, dict):
        w("{")
        for i, (key, v) in enumerate(obj.items()):
            w((", " if i else "") + json.dumps(str(key)) + ": ")
            write_json(v, fp)
        w("}")
    elif isinstance(obj, (list, tuple)) and any(isinstance(v, (np.ndarray, StoredArray, RowsOrNone, dict))
                                                for v in obj):
        w("[")
        for i, v in enumerate(obj):
            if i:
                w(", ")
            write_json(v, fp)
        w("]")
    elif isinstance(obj, (np.ndarray, StoredArray)):  # a StoredArray: read from its file a block at a time
        _json_array(obj, w)
    elif isinstance(obj, RowsOrNone):
        _json_array(obj.values, w, obj.mask)
    else:
        w(json.dumps(_clean(obj)))


def to_lists(obj: Any) -> Any:
    """A summary with numpy arrays -> the same with plain lists (what ``json.loads(write_json(...))`` gives)."""
    if isinstance(obj, dict):
        return {k: to_lists(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_lists(v) for v in obj]
    if isinstance(obj, (np.ndarray, StoredArray, RowsOrNone)):
        return _clean(obj.tolist())
    return obj


#: the per-stage times, read only for the timing section of live runs
TIMING_FIELDS = {"plant.u_rx_ns", "encoder.tx_ns", "controller.tx_ns", "attacker.tx_ns"}


#: what the resimulation and the actuation section read beyond the summary's fields
REPLAY_FIELDS = {"plant.delay_ns", "plant.x_meas", "encoder.q", "encoder.xi", "encoder.saturated", "controller.q",
                 "controller.xi", "controller.u", "plant.u"}


#: what a live run's summary decodes (the launcher's, and ``testbed report`` of a live recording)
LIVE_FIELDS = SUMMARY_FIELDS | REPLAY_FIELDS


def _fields(meta: dict) -> set[str]:
    live = meta.get("testbed.run", {}).get("source") == "live"
    return LIVE_FIELDS if live else (SUMMARY_FIELDS - TIMING_FIELDS) | REPLAY_FIELDS


def _may_measure(meta: dict, sc: Scenario) -> bool:
    """Whether a recording can hold x_meas (what a sensor read): a live run's plant may be a device that
    sends it; ``testbed simulate`` writes it only for a scenario with a ``[plant.sensor]``."""
    if meta.get("testbed.run", {}).get("source") != "simulate":
        return True
    return sc.plant.device is not None and sc.plant.device.sensor is not None


def _may_delay(meta: dict, sc: Scenario) -> bool:
    """Whether anything reads a recording's ``delay_ns``: the actuation section and the resimulation of a run
    under physical timing, and a live run's timing arrays (``testbed.runs.run``); a simulation under ideal
    timing records 0 in every sample."""
    return meta.get("testbed.run", {}).get("source") != "simulate" or sc.run.timing == "physical"


def load(path: str | Path, *, fields: set[str] | Callable[[dict], set[str] | None] | None = _fields,
         trust_code: bool = False, note: bool = True) -> tuple[Columns, Scenario]:
    """The columns of a recording and its scenario (``BadInput`` for anything unusable).

    ``fields``: what to decode (``read_columns``; default what the report reads, None: every field).
    ``trust_code``: run a plant's or method's source stored in the recording when its module is not
    importable (``--trust-code``; otherwise a stand-in and, unless not ``note``, a line on stderr:
    ``recorded.recorded_scenario``).
    The columns carry ``plant_source`` and ``model_source`` (``recorded.recorded_scenario``).
    """
    from .columns import read_columns
    from .mcapfile import read_metadata
    from .recorded import recorded_scenario

    meta, _ = read_metadata(path)
    sc, ps, ms = recorded_scenario(meta, str(path), trust_code=trust_code, note=note)
    if callable(fields):
        fields = fields(meta)
    if fields is not None and "plant.x_meas" in fields and not _may_measure(meta, sc):
        fields = fields - {"plant.x_meas"}  # a simulation writes x_meas only with a sensor: 2n columns less
    if fields is not None and "plant.delay_ns" in fields and not _may_delay(meta, sc):
        fields = fields - {"plant.delay_ns"}  # read only under physical timing or for a live run's arrays
    if fields is not None and sc.run.timing == "physical":
        fields = fields | {"plant.u_rx_ns"}  # when u_k arrived: the report's actuation section, a simulation's too
    cols = read_columns(path, fields=fields, sc=sc, metadata=meta)
    cols.plant_source, cols.model_source = ps, ms
    return cols, sc
