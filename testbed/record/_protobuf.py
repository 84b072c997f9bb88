"""numba parser of MCAP chunk records and the protobuf wire format of the four telemetry schemas.

Used by ``testbed.record.columns`` (which documents the layout of the tables); kept
apart so that importing the reader stays cheap until a file is read.  Every
read is bounds-checked: a crafted buffer makes a message malformed (counted,
never half-written) or the chunk corrupt (status 2), never an out-of-bounds access.

Indices are cast to unsigned (``np.uint64(p)``) where they are used: numba gives a
signed index Python's meaning (negative counts from the end), a test and a branch
on every access, and none of the walk's indices can be negative (each is a
position from 0 upwards, checked against its bound before it is used, or a
column of the reader's own layout).  With unsigned indices LLVM also reads an
8-byte field with one load (docs/benchmarks.md, "Post-mortems against the disk").
"""

from __future__ import annotations

import numpy as np
from numba import njit

# keep in step with testbed/record/columns.py
G_SKIP, G_I64, G_I32, G_U8, G_F64, G_VEC, G_K, G_U32 = range(8)
CH_UNKNOWN, CH_COUNT, CH_PYTHON, CH_TELEMETRY = 0, 1, 2, 3
OP_MESSAGE = 5
FLAG_FINAL = 8
MAX_FIELD = 64
MSG_HEAD = 22          # channel id u16, sequence u32, log time u64, publish time u64


@njit(cache=True, nogil=True)
def _varint(buf, p, end):
    """(value as uint64, next position); position -1 when the varint runs past ``end`` or on (> 10 bytes).

    A one-byte varint (keys, flags, small values) returns at once; longer ones read at most 10 bytes (the 10th
    byte's bits above 2^64 are dropped, as protobuf's parsers drop them)."""
    if p < end:
        b = buf[np.uint64(p)]
        if b < 0x80:
            return np.uint64(b), p + 1
    r = np.uint64(0)
    s = np.uint64(0)
    q = p
    lim = min(end, p + 10)
    while q < lim:
        b = buf[np.uint64(q)]
        q += 1
        r |= np.uint64(b & 0x7F) << s
        s += np.uint64(7)
        if b < 0x80:
            return r, q
    return r, -1


@njit(cache=True, nogil=True)
def _u64(buf, p):
    q = np.uint64(p)
    v = np.uint64(0)
    for i in range(8):   # unsigned indices: LLVM makes one 8-byte load of these
        v |= np.uint64(buf[q + np.uint64(i)]) << np.uint64(8 * i)
    return v


@njit(cache=True, nogil=True)
def _parse(buf, a, b, tgt, r, s0, s1, s2, s3, fcount, fbits, fvals, vfs, nv):
    """One telemetry message ``buf[a:b]`` into the scratch rows s0..s3; returns k, or -1 if malformed.
    ``tgt[r]``: the map of role ``r``; ``vfs[r, :nv]``: its vector fields (the only ones ``fcount`` counts)."""
    k = np.int64(0)
    ur = np.uint64(r)
    for i in range(nv):
        fcount[np.uint64(vfs[ur, np.uint64(i)])] = 0
    p = a
    while p < b:
        key, p = _varint(buf, p, b)
        if p < 0:
            return -1
        f = np.int64(key >> np.uint64(3))
        wt = np.int64(key & np.uint64(7))
        if f == 0:
            return -1
        g = 0
        col = 0
        w = 0
        if f < MAX_FIELD:
            uf = np.uint64(f)
            g = tgt[ur, uf, np.uint64(0)]
            col = tgt[ur, uf, np.uint64(1)]
            w = tgt[ur, uf, np.uint64(2)]
        if g == G_SKIP:
            if wt == 0:
                _v, p = _varint(buf, p, b)
                if p < 0:
                    return -1
            elif wt == 1:
                p += 8
            elif wt == 2:
                ln, p = _varint(buf, p, b)
                if p < 0 or ln > np.uint64(b - p):
                    return -1
                p += np.int64(ln)
            elif wt == 5:
                p += 4
            else:
                return -1
            if p > b:
                return -1
            continue
        if g == G_F64:
            if wt != 1 or p + 8 > b:
                return -1
            fbits[0] = _u64(buf, p)
            s3[np.uint64(col)] = fvals[0]
            p += 8
            continue
        if g == G_VEC:
            if wt == 2:
                ln, p = _varint(buf, p, b)
                if p < 0 or ln > np.uint64(b - p) or ln % np.uint64(8) != np.uint64(0):
                    return -1
                cnt = np.int64(ln) // 8
            elif wt == 1:
                cnt = 1
                if p + 8 > b:
                    return -1
            else:
                return -1
            uf = np.uint64(f)
            c0 = fcount[uf]
            if c0 + cnt > w:
                return -1
            for i in range(c0, c0 + cnt):
                fbits[0] = _u64(buf, p)
                s3[np.uint64(col + i)] = fvals[0]
                p += 8
            fcount[uf] = c0 + cnt
            continue
        # varint groups
        if wt != 0:
            return -1
        v, p = _varint(buf, p, b)
        if p < 0:
            return -1
        if g == G_K:
            k = np.int64(v & np.uint64(0xFFFFFFFF))
        elif g == G_I64:
            s0[np.uint64(col)] = np.int64(v)
        elif g == G_U32:
            s0[np.uint64(col)] = np.int64(v & np.uint64(0xFFFFFFFF))
        elif g == G_I32:
            lo = np.int64(v & np.uint64(0xFFFFFFFF))
            if lo >= 2147483648:
                lo -= 4294967296
            s1[np.uint64(col)] = np.int32(lo)
        elif g == G_U8:
            lo = np.int64(v & np.uint64(0xFFFFFFFF))
            if lo > 255:
                return -1
            s2[np.uint64(col)] = np.uint8(lo)
    # a vector is absent (NaN) or has exactly its width
    for i in range(nv):
        f = vfs[r, i]
        if fcount[f] != 0 and fcount[f] != tgt[r, f, 2]:
            return -1
    return k


@njit(cache=True, nogil=True)
def walk(buf, pos, chan_mode, chan_role, chan_counts, tgt, ranges, N, rows, T0, T1, T2, T3, present,
         D0, D1, D2, D3, flags_col, F0, F1, F2, F3, final_k, stats, role_stats, py_pos):
    """Walk the records of ``buf`` from ``pos``: decode telemetry, count the rest.

    Returns ``(pos, status, n_py)``: status 0 at the end of ``buf``; 1 stopped at a
    record Python must handle first (a schema or channel record, anything but a
    message) at ``pos``; 2 a record runs past the end (corrupt).  ``py_pos[:n_py]``:
    offsets of the messages of channels decoded in Python (events, status, ...).
    ``stats``: [0] largest log time, [1] messages of unregistered channels.
    ``role_stats[r]``: malformed, k >= N, duplicates, k < N but beyond the rows allocated, final samples.
    """
    n = buf.size
    n_py = 0
    s0 = D0.copy()
    s1 = D1.copy()
    s2 = D2.copy()
    s3 = D3.copy()
    fcount = np.zeros(MAX_FIELD, dtype=np.int64)
    fbits = np.zeros(1, dtype=np.uint64)
    fvals = fbits.view(np.float64)          # fbits' 8 bytes read as a double (one view, made once)
    nroles = tgt.shape[0]
    vfs = np.zeros((nroles, MAX_FIELD), dtype=np.int64)   # each role's vector fields
    nvs = np.zeros(nroles, dtype=np.int64)
    for r in range(nroles):
        for f in range(MAX_FIELD):
            if tgt[r, f, 0] == G_VEC:
                vfs[r, nvs[r]] = f
                nvs[r] += 1
    while pos < n:
        if pos + 9 > n:
            return pos, 2, n_py
        op = buf[np.uint64(pos)]
        ln = _u64(buf, pos + 1)
        if ln > np.uint64(n - pos - 9):
            return pos, 2, n_py
        body = pos + 9
        end = body + np.int64(ln)
        if op != OP_MESSAGE:
            return pos, 1, n_py
        if end - body < MSG_HEAD:
            return pos, 2, n_py
        cid = np.uint64(buf[np.uint64(body)]) | (np.uint64(buf[np.uint64(body + 1)]) << np.uint64(8))
        mode = chan_mode[cid]
        if mode == CH_UNKNOWN:
            stats[1] += 1
            pos = end
            continue
        chan_counts[cid] += 1
        lt = np.int64(_u64(buf, body + 6))
        if lt > stats[0]:
            stats[0] = lt
        if mode == CH_PYTHON:
            py_pos[n_py] = pos
            n_py += 1
        elif mode == CH_TELEMETRY:
            r = chan_role[cid]
            rg = ranges[np.uint64(r)]
            lo0, hi0 = rg[0, 0], rg[0, 1]
            lo1, hi1 = rg[1, 0], rg[1, 1]
            lo2, hi2 = rg[2, 0], rg[2, 1]
            lo3, hi3 = rg[3, 0], rg[3, 1]
            for i in range(lo0, hi0):
                s0[np.uint64(i)] = D0[np.uint64(i)]
            for i in range(lo1, hi1):
                s1[np.uint64(i)] = D1[np.uint64(i)]
            for i in range(lo2, hi2):
                s2[np.uint64(i)] = D2[np.uint64(i)]
            for i in range(lo3, hi3):
                s3[np.uint64(i)] = D3[np.uint64(i)]
            k = _parse(buf, body + MSG_HEAD, end, tgt, r, s0, s1, s2, s3, fcount, fbits, fvals, vfs, nvs[r])
            if k < 0:
                role_stats[r, 0] += 1
            elif r == 0 and flags_col >= 0 and (s2[flags_col] & FLAG_FINAL) != 0:
                if k > N or k > rows:
                    role_stats[r, 1] += 1
                else:
                    F0[lo0:hi0] = s0[lo0:hi0]
                    F1[lo1:hi1] = s1[lo1:hi1]
                    F2[lo2:hi2] = s2[lo2:hi2]
                    F3[lo3:hi3] = s3[lo3:hi3]
                    final_k[0] = k
                    role_stats[r, 4] += 1
            elif k >= N:
                role_stats[r, 1] += 1
            elif k >= rows:
                role_stats[r, 3] += 1
            else:
                uk = np.uint64(k)
                if present[uk, np.uint64(r)] != 0:
                    role_stats[r, 2] += 1
                present[uk, np.uint64(r)] = 1
                for i in range(lo0, hi0):
                    T0[uk, np.uint64(i)] = s0[np.uint64(i)]
                for i in range(lo1, hi1):
                    T1[uk, np.uint64(i)] = s1[np.uint64(i)]
                for i in range(lo2, hi2):
                    T2[uk, np.uint64(i)] = s2[np.uint64(i)]
                for i in range(lo3, hi3):
                    T3[uk, np.uint64(i)] = s3[np.uint64(i)]
        pos = end
    return pos, 0, n_py
