"""The telemetry of a simulated run encoded in bulk: every sample's protobuf message from the arrays at once.

``record_simulation`` (``testbed.record.recording``) writes a simulation with the topics and
schemas of a live run.  Built one dataclass and one protobuf object a message, the messages
cost far more than the writer; here the four telemetry messages of every sample (``PlantSample``,
``EncoderSample``, ``AttackerSample``, ``ControllerSample``) are encoded by one compiled pass
over numpy columns into one buffer, in the protobuf wire format with the field numbers of
``testbed.record.schema.SPEC``.  The bytes are those ``schema.to_pb(...).SerializeToString()``
gives for the same message (fields in number order, proto3 defaults left out, optional
fields present or absent, repeated doubles packed), which ``tests/record/test_simrecord.py`` checks
message by message; :func:`fast_adder` then adds them to mcap's writer without its per-message
objects.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numba as nb
import numpy as np

from . import schema

if TYPE_CHECKING:
    from ..sim.loop import SimResult

# field kinds of the encoder
VARINT, VARINT_OPT, DOUBLE, DOUBLE_OPT, PACKED, HEADER = range(6)

_U7F = np.uint64(0x7F)
_U80 = np.uint64(0x80)
_S7 = np.uint64(7)
_S8 = np.uint64(8)
_UFF = np.uint64(0xFF)


@nb.njit(cache=True)
def _vlen(u):
    n = 1
    while u >= _U80:
        u >>= _S7
        n += 1
    return n


@nb.njit(cache=True)
def _put(out, pos, u):
    while u >= _U80:
        out[pos] = np.uint8((u & _U7F) | _U80)
        u >>= _S7
        pos += 1
    out[pos] = np.uint8(u)
    return pos + 1


@nb.njit(cache=True)
def _put_f64(out, pos, bits):
    for _ in range(8):
        out[pos] = np.uint8(bits & _UFF)
        bits >>= _S8
        pos += 1
    return pos


@nb.njit(cache=True)
def _encode(kinds, numbers, cols, I, Ipres, D, Dpres, R, Rlen, H, out, offs):
    """Messages k = 0..N-1 into ``out``; message k is out[offs[k]:offs[k+1]].  I: (N, .) uint64 (int64 bits),
    D: (N, .) uint64 (float64 bits), R: (N, ., w) uint64 (float64 bits), H: (N,) int64 absolute ns."""
    N = offs.shape[0] - 1
    pos = 0
    for k in range(N):
        offs[k] = pos
        for f in range(kinds.shape[0]):
            kind = kinds[f]
            num = np.uint64(numbers[f])
            c = cols[f]
            if kind == VARINT or kind == VARINT_OPT:
                v = I[k, c]
                if (kind == VARINT and v != 0) or (kind == VARINT_OPT and Ipres[k, c]):
                    pos = _put(out, pos, num << np.uint64(3))
                    pos = _put(out, pos, v)
            elif kind == DOUBLE or kind == DOUBLE_OPT:
                v = D[k, c]
                if (kind == DOUBLE and v != 0) or (kind == DOUBLE_OPT and Dpres[k, c]):
                    pos = _put(out, pos, (num << np.uint64(3)) | np.uint64(1))
                    pos = _put_f64(out, pos, v)
            elif kind == PACKED:
                L = Rlen[k, c]
                if L > 0:
                    pos = _put(out, pos, (num << np.uint64(3)) | np.uint64(2))
                    pos = _put(out, pos, np.uint64(8 * L))
                    for j in range(L):
                        pos = _put_f64(out, pos, R[k, c, j])
            else:  # HEADER: testbed.Header { stamp: google.protobuf.Timestamp { seconds, nanos } }
                h = H[k]
                sec = h // 1_000_000_000
                ns = h - sec * 1_000_000_000
                usec = np.uint64(sec)
                uns = np.uint64(ns)
                ts = 0
                if sec != 0:
                    ts += 1 + _vlen(usec)
                if ns != 0:
                    ts += 1 + _vlen(uns)
                stamp = 1 + _vlen(np.uint64(ts)) + ts
                pos = _put(out, pos, (num << np.uint64(3)) | np.uint64(2))
                pos = _put(out, pos, np.uint64(stamp))
                pos = _put(out, pos, np.uint64(10))   # field 1 (stamp), length-delimited
                pos = _put(out, pos, np.uint64(ts))
                if sec != 0:
                    pos = _put(out, pos, np.uint64(8))
                    pos = _put(out, pos, usec)
                if ns != 0:
                    pos = _put(out, pos, np.uint64(16))
                    pos = _put(out, pos, uns)
    offs[N] = pos


def encode(name: str, N: int, cols: dict) -> list[bytes]:
    """N messages of schema ``name`` (``schema.SPEC``) from columns; one ``bytes`` each.

    ``cols``: field -> value; an integer or double field: an (N,) array, or (values, present) for an
    optional one (``?``); a repeated field (``*``): (values (N, w), lengths (N,)); ``header``: (N,)
    absolute ns.  A field not in ``cols`` is absent from every message.
    """
    kinds, numbers, where = [], [], []
    ints: list[np.ndarray] = []
    dbls: list[np.ndarray] = []
    reps: list[np.ndarray] = []
    ipres, dpres, rlens = [], [], []
    H = np.zeros(N, dtype=np.int64)
    for num, (f, t, _doc) in enumerate(schema.SPEC[name], start=1):
        if f not in cols:
            continue
        v = cols[f]
        base = t.rstrip("?*")
        opt = t.endswith("?")
        numbers.append(num)
        if base == "hdr":
            kinds.append(HEADER)
            where.append(0)
            H = np.asarray(v, dtype=np.int64)
        elif t.endswith("*"):
            vals, lens = v
            kinds.append(PACKED)
            where.append(len(reps))
            reps.append(np.asarray(vals, dtype=np.float64).reshape(N, -1))
            rlens.append(np.asarray(lens, dtype=np.int64))
        elif base == "f64":
            vals, pres = v if opt else (v, None)
            kinds.append(DOUBLE_OPT if opt else DOUBLE)
            where.append(len(dbls))
            dbls.append(np.broadcast_to(np.asarray(vals, dtype=np.float64), (N,)))
            dpres.append(np.ones(N, dtype=bool) if pres is None else np.broadcast_to(pres, (N,)))
        else:
            vals, pres = v if opt else (v, None)
            kinds.append(VARINT_OPT if opt else VARINT)
            where.append(len(ints))
            ints.append(np.broadcast_to(np.asarray(vals, dtype=np.int64), (N,)))
            ipres.append(np.ones(N, dtype=bool) if pres is None else np.broadcast_to(pres, (N,)))
    I = np.ascontiguousarray(np.stack(ints, axis=1) if ints else np.zeros((N, 0), np.int64)).view(np.uint64)
    Ip = np.ascontiguousarray(np.stack(ipres, axis=1) if ipres else np.zeros((N, 0), bool))
    D = np.ascontiguousarray(np.stack(dbls, axis=1) if dbls else np.zeros((N, 0))).view(np.uint64)
    Dp = np.ascontiguousarray(np.stack(dpres, axis=1) if dpres else np.zeros((N, 0), bool))
    w = max([r.shape[1] for r in reps] + [1])
    R = np.zeros((N, len(reps), w))
    for i, r in enumerate(reps):
        R[:, i, :r.shape[1]] = r
    R = R.view(np.uint64)
    Rl = np.ascontiguousarray(np.stack(rlens, axis=1) if rlens else np.zeros((N, 0), np.int64))
    bound = 40 + 11 * I.shape[1] + 10 * D.shape[1] + len(reps) * (12 + 8 * w)
    out = np.empty(N * bound + 1, dtype=np.uint8)
    offs = np.zeros(N + 1, dtype=np.int64)
    _encode(np.asarray(kinds, np.int64), np.asarray(numbers, np.int64), np.asarray(where, np.int64), I, Ip, D, Dp,
            R, Rl, H, out, offs)
    data = out[:offs[-1]].tobytes()
    o = offs.tolist()
    return [data[o[k]:o[k + 1]] for k in range(N)]


def _log10(E: np.ndarray):
    """log10 E_k where E_k > 0 is finite (``math.log10``, as the per-message path), and where it is."""
    ok = np.isfinite(E) & (E > 0)
    out = np.zeros(len(E))
    out[ok] = np.fromiter(map(math.log10, E[ok].tolist()), dtype=np.float64, count=int(ok.sum()))
    return out, ok


def telemetry_columns(res: SimResult, k0: int, k1: int, t0: int, Tn: int, attack_on: np.ndarray,
                      dropped_total: np.ndarray, reason: np.ndarray, drop: np.ndarray | None = None) -> dict:
    """The columns of the four telemetry messages of samples k0..k1-1 of a ``SimResult`` (what
    ``record_simulation``'s per-message path puts in each): schema name -> columns for :func:`encode`."""
    N = k1 - k0
    sl = slice(k0, k1)
    ks = np.arange(k0, k1, dtype=np.int64)
    tk = ks * Tn
    hdr = t0 + tk
    yes = np.ones(N, dtype=bool)
    n, m = res.x.shape[1], res.u.shape[1]
    th = np.asarray(res.theta[sl], dtype=np.int64)
    dk = np.zeros(N, np.int64) if res.delays is None else np.asarray(res.delays[sl], dtype=np.int64)
    miss = np.zeros(N, bool) if res.u_missing is None else np.asarray(res.u_missing[sl], dtype=bool)
    held = np.zeros(N, bool) if res.withheld is None else np.asarray(res.withheld[sl], dtype=bool)
    u_plant = getattr(res, "u_plant", None)
    u = np.where(miss[:, None], 0.0, res.u[sl]) if u_plant is None else u_plant[sl]
    fs = np.where(ks == res.diverged_at, int(res.flow_status), 0)
    plant = {"k": ks, "t_ns": (tk, yes), "sensor_tx_ns": (tk, yes), "u_rx_ns": (tk + dk, ~miss), "delay_ns": dk,
             "theta": np.where(miss, 255, th), "flags": np.where(miss, 3, 0), "flow_status": fs,
             "x": (res.x[sl], np.full(N, n)), "u": (u, np.full(N, m)), "header": hdr}
    x_meas = getattr(res, "x_meas", None)
    if x_meas is not None:  # what the sensor read ([plant.sensor])
        plant["x_meas"] = (x_meas[sl], np.full(N, n))
    sym = np.asarray(res.symbols[sl], dtype=np.int64)
    E = np.where(held, np.nan, res.E_enc[sl])
    lg, has = _log10(E)
    keep = np.where(held, 0, n)
    enc = {"k": ks, "sensor_tx_ns": (tk, yes), "rx_ns": (tk, yes), "tx_ns": (tk, ~held),
           "symbol": np.where(held, -1, sym), "saturated": np.where(held, 0, res.saturated[sl]), "silent": held,
           "E": E, "xi": (res.xi_enc[sl], keep), "q": (res.q_enc[sl], keep), "header": hdr, "log10_E": (lg, has)}
    tot = np.asarray(dropped_total[sl], dtype=np.int64)
    dr = th if drop is None else np.asarray(drop[sl], dtype=np.int64)   # the attacker's own drops
    att = {"k": ks, "rx_ns": (tk, yes), "tx_ns": (tk, dr == 0), "dropped": dr, "corrupted": np.zeros(N, np.int64),
           "attack_on": np.asarray(attack_on[sl], dtype=np.int64), "dropped_total": tot,
           "forwarded_total": ks + 1 - tot, "header": hdr}
    rs = np.asarray(reason[sl], dtype=np.int64)
    rec = rs == 0
    Ed = np.asarray(res.E_dec[sl], dtype=np.float64)
    lgd, hasd = _log10(Ed)
    full = np.full(N, n)
    ctl = {"k": ks, "sym_stamp_ns": (tk, rec), "rx_ns": (tk, rec), "tx_ns": (tk, yes), "symbol": np.where(rec, sym, -1),
           "theta": th, "reason": rs, "E": Ed, "xi": (res.xi_dec[sl], full), "q": (res.q[sl], full),
           "u": (res.u[sl], np.full(N, m)), "header": hdr, "log10_E": (lgd, hasd)}
    return {"PlantSample": plant, "EncoderSample": enc, "AttackerSample": att, "ControllerSample": ctl}


def fast_adder(writer: Any) -> Callable[[int, int, bytes, int], None]:
    """``add(channel_id, log_time, data, publish_time)`` for mcap's ``Writer`` (chunked), 2-3 times
    cheaper than its ``add_message`` (measured: ``tests/record/test_simrecord.py``, whose test of this fails when
    mcap's private state it writes into changes): the same Message record, chunk index and statistics, kept in the
    writer's own state (so its ``add_message``, ``flush`` and ``finish`` go on as if it had written them;
    ``tests/record/test_simrecord.py`` checks the files are byte for byte the same).  The messages must come in
    order of log time (a simulation's do).  A writer whose internals differ from mcap 1.x's: its own
    ``add_message``."""
    import struct

    from mcap.records import MessageIndex

    try:
        st = writer._Writer__statistics
        cb = writer._Writer__chunk_builder
        size = writer._Writer__chunk_size
        finalize = writer._Writer__finalize_chunk
        counts = st.channel_message_counts
        cb.record_writer._buffer, cb.message_indices, cb.num_messages  # noqa: B018 - present?
    except AttributeError:
        return writer.add_message
    if cb is None:
        return writer.add_message
    pack = struct.Struct("<BQHIQQ").pack

    def add(channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        if st.message_count == 0:
            st.message_start_time = log_time
        elif log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        counts[channel_id] += 1
        st.message_count += 1
        buf = cb.record_writer._buffer
        if cb.num_messages == 0:
            cb.message_start_time = log_time
        elif log_time < cb.message_start_time:
            cb.message_start_time = log_time
        if log_time > cb.message_end_time:
            cb.message_end_time = log_time
        idx = cb.message_indices.get(channel_id)
        if not idx:
            idx = cb.message_indices[channel_id] = MessageIndex(channel_id=channel_id, records=[])
        pos = buf.tell()
        idx.records.append((log_time, pos))
        cb.num_messages += 1
        buf.write(pack(5, 22 + len(data), channel_id, 0, log_time, publish_time))
        buf.write(data)
        if pos + 31 + len(data) > size:
            finalize()

    return add
