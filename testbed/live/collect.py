"""The launcher's collector: subscribes to a run's telemetry, events and liveliness.

Everything arrives over Zenoh as it happens, so a node killed mid-run leaves
its telemetry up to the kill.  ``snapshot(sc)`` hands it, as columns, to
``testbed.record.summary.build_summary`` (shared with ``testbed report``).

With a ``spill`` file (the launcher's: ``telemetry.bin`` in the run folder) the records are
appended there as they arrive and only the last ``RECENT`` of each node stay in memory, so that
the launcher's memory stays flat however long the run.  At the end the file is read back in
chunks of ``Spill.CHUNK`` bytes (``Spill.records``): through each node's digest (``telemetry_check``)
and, as rows of numpy columns ``SpillRows.CHUNK`` samples at a time in the order of k (``rows``), into
the summary, whose every reduction is made chunk by chunk; never as one object per record, nor as
whole columns (``snapshot`` still gives those, for a caller that wants them).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import heapq
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..record.faults import Fault
from ..wire import messages as msg
from ..wire import transport

if TYPE_CHECKING:
    from ..record.columns import ColumnBuilder, Columns
    from ..record.summary import ColumnChunks
    from ..scenario import Scenario

PT = msg.PlantTelemetry


class Spill:
    """The collector's telemetry file: ``(role index u8, length u32 LE, record)`` appended as records arrive."""

    HEAD = struct.Struct("<BI")
    #: bytes read at a time at the end of the run (a record longer than this is read whole)
    CHUNK = 1 << 20

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.f = open(self.path, "w+b", buffering=1 << 20)

    def write(self, ri: int, b: bytes) -> None:
        self.f.write(self.HEAD.pack(ri, len(b)) + b)

    def records(self, chunk: int | None = None) -> Iterator[tuple[int, bytes]]:
        """Every ``(role index, record bytes)`` in the order written, read ``chunk`` bytes at a time."""
        for buf, ris, offs, lens in self.blocks(chunk):
            for ri, o, n in zip(ris.tolist(), offs.tolist(), lens.tolist(), strict=True):
                yield ri, buf[o:o + n]

    def blocks(self, chunk: int | None = None) -> Iterator[tuple[bytes, np.ndarray, np.ndarray, np.ndarray]]:
        """The file ``chunk`` bytes at a time: ``(bytes, role indices, offsets, lengths)`` of the whole records
        in each read (the arrays index the bytes), in the order written."""
        self.f.flush()
        with open(self.path, "rb") as f:  # its own handle: the writer's position stays at the end
            yield from _file_blocks(f, int(chunk or self.CHUNK))

    def decoded(self) -> Iterator[tuple[int, Any]]:
        """Every ``(role index, telemetry dataclass)``, as ``records`` reads them."""
        types = [msg.TELEMETRY_TYPES[r] for r in transport.ROLES]
        for ri, b in self.records():
            yield ri, types[ri].decode(b)

    def close(self) -> None:
        self.f.close()


def _file_blocks(f: Any, chunk: int) -> Iterator[tuple[bytes, np.ndarray, np.ndarray, np.ndarray]]:
    """``Spill.blocks`` of an open file, from its position."""
    unpack, hs = Spill.HEAD.unpack_from, Spill.HEAD.size
    buf = b""
    while True:
        more = f.read(chunk)
        buf = buf + more if buf else more
        ris, offs, lens = [], [], []
        off, size = 0, len(buf)
        while off + hs <= size:
            ri, n = unpack(buf, off)
            if off + hs + n > size:
                break
            ris.append(ri)
            offs.append(off + hs)
            lens.append(n)
            off += hs + n
        if ris:
            yield (buf, np.array(ris, dtype=np.int64), np.array(offs, dtype=np.int64), np.array(lens, dtype=np.int64))
        buf = buf[off:]
        if not more:
            return


class Collector:
    """Telemetry, events, node summaries, start/stop and liveliness of one run."""

    #: events kept (the rest are counted): a flood cannot grow the launcher without bound
    MAX_EVENTS = 10_000
    #: records of each node kept in memory when they are spilled to a file (the stall watch reads them)
    RECENT = 1024
    #: records of a node the telemetry digest holds back at most to put them in the order of k
    MAX_HELD = 1 << 16

    def __init__(self, session: Any, keys: transport.Keys, n_steps: int, spill: str | Path | None = None) -> None:
        import zenoh

        self._zenoh = zenoh
        self.keys = keys
        self.n_steps = int(n_steps)
        self.rejected = 0        # telemetry records for a sample outside [0, N), or a second copy of one
        self.events_dropped = 0
        self.lock = threading.Lock()
        # each role's telemetry records by k (of ``msg.TELEMETRY_TYPES[role]``): all, or the recent ones
        self.tele: dict[str, dict[int, Any]] = {r: {} for r in transport.ROLES}
        self._seen = {r: bytearray(self.n_steps // 8 + 1) for r in transport.ROLES}  # one bit per sample
        self._spill = None if spill is None else Spill(spill)
        self.top: dict[str, int] = dict.fromkeys(transport.ROLES, -1)  # each role's highest k so far
        self.received: dict[str, int] = dict.fromkeys(transport.ROLES, 0)  # records kept, the plant's final one too
        self.lag = 0  # how far a record's k fell behind the highest k of any role before it (``SpillRows``)
        self.lag_of: dict[str, int] = dict.fromkeys(transport.ROLES, 0)  # ... of its own role (a node's own order)
        self._top_all = -1
        self.plant_final: msg.PlantTelemetry | None = None
        self.events: list[msg.Event] = []
        self.summaries: dict[str, dict] = {}
        self.status: list[msg.AttackerStatus] = []
        self.start: msg.Start | None = None
        self.start_rx_mono = 0
        self.stops: list[msg.Stop] = []
        self.liveliness: list[tuple[int, str, bool]] = []  # (monotonic ns, node, alive)
        self.alive: set[str] = set()
        self.ready: set[str] = set()
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
            session.liveliness().declare_subscriber(keys.ready("*"), self._on_ready, history=True),
        ]

    @property
    def role_lag(self) -> int:
        """How far a record's k fell behind the highest k of its own role before it, the largest over the roles."""
        return max(self.lag_of.values())

    def _on_telemetry(self, sample: Any) -> None:
        role = transport.Keys.node_of(sample.key_expr)
        typ = msg.TELEMETRY_TYPES.get(role)
        if typ is None:
            return
        try:
            raw = list(msg.unpack_batch(sample.payload))
            recs = [typ.decode(r) for r in raw]
        except msg.MessageError:
            self.bad += 1
            return
        N = self.n_steps
        ri = transport.ROLES.index(role)
        with self.lock:
            d, seen = self.tele[role], self._seen[role]
            for t, b in zip(recs, raw):
                if role == "plant" and t.flags & PT.FLAG_FINAL:
                    if not 0 <= t.k <= N or self.plant_final is not None:
                        self.rejected += 1
                        continue
                    self.plant_final = t
                    self.received[role] += 1
                elif not 0 <= t.k < N or seen[t.k >> 3] & (1 << (t.k & 7)):
                    self.rejected += 1  # never stored: a k from the wire sizes nothing
                else:
                    seen[t.k >> 3] |= 1 << (t.k & 7)
                    d[t.k] = t
                    self.received[role] += 1
                    if t.k > self.top[role]:
                        self.top[role] = t.k
                    elif self.top[role] - t.k > self.lag_of[role]:
                        self.lag_of[role] = self.top[role] - t.k
                    if t.k > self._top_all:
                        self._top_all = t.k
                    elif self._top_all - t.k > self.lag:
                        self.lag = self._top_all - t.k
                    if self._spill is not None:
                        self._spill.write(ri, bytes(b))
            if self._spill is not None and len(d) > 2 * self.RECENT:
                keep = self.top[role] - self.RECENT
                for k in [k for k in d if k < keep]:
                    del d[k]

    def _on_event(self, sample: Any) -> None:
        try:
            e = msg.Event.decode(sample.payload)
        except msg.MessageError:
            self.bad += 1
            return
        with self.lock:
            if len(self.events) < self.MAX_EVENTS:
                self.events.append(e)
            else:
                self.events_dropped += 1

    def _on_summary(self, sample: Any) -> None:
        try:
            s = msg.NodeSummary.decode(sample.payload)
        except msg.MessageError:
            self.bad += 1
            return
        if s.node != transport.Keys.node_of(sample.key_expr) or s.node not in transport.ROLES:
            self.bad += 1
            return
        with self.lock:
            self.summaries[s.node] = s.data

    def _on_status(self, sample: Any) -> None:
        try:
            s = msg.AttackerStatus.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            if len(self.status) < self.MAX_EVENTS:
                self.status.append(s)

    def _on_start(self, sample: Any) -> None:
        try:
            s = msg.Start.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            if self.start is None:
                self.start = s
                self.start_rx_mono = time.monotonic_ns()

    def _on_stop(self, sample: Any) -> None:
        try:
            s = msg.Stop.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            if len(self.stops) < 100:
                self.stops.append(s)

    def _on_alive(self, sample: Any) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        alive = sample.kind != self._zenoh.SampleKind.DELETE
        with self.lock:
            self.liveliness.append((time.monotonic_ns(), node, alive))
            (self.alive.add if alive else self.alive.discard)(node)

    def _on_ready(self, sample: Any) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        with self.lock:
            (self.ready.discard if sample.kind == self._zenoh.SampleKind.DELETE else self.ready.add)(node)

    # ---- queries
    def ready_nodes(self) -> set[str]:
        with self.lock:
            return set(self.ready)

    def last_k(self, role: str) -> int:
        with self.lock:
            return self.top.get(role, -1)

    def record(self, role: str, k: int) -> Any:
        """``role``'s telemetry record of sample ``k``, or None."""
        with self.lock:
            return self.tele[role].get(k)

    def first_after(self, role: str, k: int) -> Any:
        """``role``'s first telemetry record after sample ``k``, or None."""
        with self.lock:
            d = self.tele[role]
            return next((d[j] for j in range(k + 1, self.top[role] + 1) if j in d), None)

    def lost_at(self, node: str) -> int | None:
        """monotonic ns at which ``node``'s liveliness token went away (last time), or None."""
        with self.lock:
            for t, n, alive in reversed(self.liveliness):
                if n == node:
                    return None if alive else t
        return None

    def snapshot_summaries(self) -> dict[str, dict]:
        with self.lock:
            return dict(self.summaries)

    def telemetry_behind(self) -> list[str]:
        """The nodes whose summary says they published more telemetry records than have arrived so far: a
        node's summary can overtake its last batches (telemetry travels at a lower priority)."""
        with self.lock:
            return [r for r, s in self.summaries.items()
                    if isinstance(s.get("telemetry_records"), int) and self.received.get(r, 0) < s["telemetry_records"]]

    def event_of(self, node: str, kind: str) -> msg.Event | None:
        """The first event ``kind`` of ``node``, or None."""
        with self.lock:
            return next((e for e in self.events if e.node == node and e.kind == kind), None)

    def plant_done(self) -> bool:
        with self.lock:
            return any(s.origin == "plant" for s in self.stops)

    def _records(self) -> Iterator[tuple[int, Any]]:
        """Every accepted ``(role index, record)`` (call with the lock held): from the spill file, a chunk at
        a time, when there is one; each role's in the order they arrived."""
        if self._spill is None:
            for ri, role in enumerate(transport.ROLES):
                for t in list(self.tele[role].values()):
                    yield ri, t
            return
        yield from self._spill.decoded()

    def _encoded(self) -> Iterator[tuple[int, int, bytes]]:
        """Every ``(role index, k, record bytes)``: a spill's as they arrived (what the node sent and digested),
        else the records kept in memory, encoded."""
        if self._spill is None:
            for ri, t in self._records():
                yield ri, t.k, t.encode()
            return
        for ri, b in self._spill.records():
            yield ri, int.from_bytes(b[:4], "little"), b

    def telemetry_check(self) -> list[Fault]:
        """Each node's own account of its telemetry (records and digest, in its summary) against what
        arrived here: a difference means records were lost, forged or altered on the way.

        The digest is over the records in the order of k (and the plant's final record last); records
        arrive in nearly that order, so it is computed in one streaming pass that holds back, for each node,
        as many records as its own records came out of their order (``lag_of``), at most ``MAX_HELD``."""
        out: list[Fault] = []
        with self.lock:
            roles = [r for r in transport.ROLES if "telemetry_sha256" in (self.summaries.get(r) or {})]
            if not roles:
                return out
            want = {transport.ROLES.index(r) for r in roles}
            h = {ri: hashlib.sha256() for ri in want}
            count = dict.fromkeys(want, 0)
            # in the order of k through a heap of each node's records that may still be overtaken: a record is
            # never more than the node's lag below its highest k before it, so one further below is final.  A
            # node whose records strayed further than ``MAX_HELD`` (one record far out of order is enough) is
            # digested again from the k order of its records, a window at a time: bounded memory, more passes
            lag = {transport.ROLES.index(r): n for r, n in self.lag_of.items()}
            heaps: dict[int, list[tuple[int, bytes]]] = {ri: [] for ri in want if lag[ri] <= self.MAX_HELD}
            top = dict.fromkeys(want, -1)
            for ri, k, b in self._encoded():
                if ri not in want:
                    continue
                count[ri] += 1
                heap = heaps.get(ri)
                if heap is None:
                    continue
                heapq.heappush(heap, (k, b))
                top[ri] = max(top[ri], k)
                while heap[0][0] < top[ri] - lag[ri]:
                    h[ri].update(heapq.heappop(heap)[1])
            for ri, heap in heaps.items():
                while heap:
                    h[ri].update(heapq.heappop(heap)[1])
            for ri in want - set(heaps):
                h[ri] = self._digest_by_k(ri)
            for ri in sorted(want):
                role = transport.ROLES[ri]
                s = self.summaries[role]
                if role == "plant" and self.plant_final is not None:
                    h[ri].update(self.plant_final.encode())
                    count[ri] += 1
                n = count[ri]
                if n != s.get("telemetry_records") or h[ri].hexdigest() != s["telemetry_sha256"]:
                    out.append(Fault(role=role, kind="telemetry_mismatch",
                                     detail=f"{n} records collected, the node published {s.get('telemetry_records')}"
                                            + ("" if n != s.get("telemetry_records") else "; digests differ")))
        return out

    def _digest_by_k(self, ri: int) -> hashlib._Hash:
        """sha256 of role ``ri``'s records in the order of k, for a node whose records strayed far from it."""
        h = hashlib.sha256()
        if self._spill is None:
            d = self.tele[transport.ROLES[ri]]
            for k in sorted(d):
                h.update(d[k].encode())
            return h
        ks = np.array([k for r, k, _ in self._encoded() if r == ri], dtype=np.int64)  # 8 bytes a record
        order = np.argsort(ks, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        # the records again, a window of ranks at a time: held at most MAX_HELD records
        for lo in range(0, len(order), self.MAX_HELD):
            got: dict[int, bytes] = {}
            i = 0
            for r, _, b in self._encoded():
                if r != ri:
                    continue
                if lo <= rank[i] < lo + self.MAX_HELD:
                    got[int(rank[i])] = b
                i += 1
            for j in range(lo, min(lo + self.MAX_HELD, len(order))):
                h.update(got[j])
        return h

    def rows(self, sc: Scenario, fields: set[str] | None = None, chunk: int | None = None) -> SpillRows | ColumnChunks:
        """What has arrived, as rows a chunk at a time (``record.summary.build_summary``: the end-of-run summary in
        bounded memory).  Read with the lock held: call once the nodes are done."""
        if self._spill is None:
            from ..record.summary import ColumnChunks

            return ColumnChunks(self.snapshot(sc, fields), chunk)
        self._spill.f.flush()
        return SpillRows(sc, self._spill.path, max(self.top.values()) + 1, self.lag, fields, chunk=chunk,
                         role_lag=self.role_lag,
                         events=self.events, status=self.status, summaries=self.summaries,
                         plant_final=self.plant_final, top=self.top)

    def snapshot(self, sc: Scenario, fields: set[str] | None = None) -> Columns:
        """What has arrived so far as columns (``testbed.record.columns.Columns``, for ``record.summary.build_summary``).

        ``fields``: the ``"role.field"`` names to decode (``columns.layout``; default all)."""
        with self.lock:
            return spill_columns(sc, self._records(), max(self.top.values()) + 1, fields, events=self.events,
                                 status=self.status, summaries=self.summaries, plant_final=self.plant_final)


def spill_columns(sc: Scenario, records: Iterable[tuple[int, Any]], rows: int, fields: set[str] | None = None, *,
                  events: Iterable[msg.Event] = (), status: Iterable[msg.AttackerStatus] = (),
                  summaries: dict[str, dict] | None = None, plant_final: msg.PlantTelemetry | None = None) -> Columns:
    """Columns (``testbed.record.columns.ColumnBuilder``) of ``rows`` samples from ``(role index, record)`` pairs
    (``Collector._records``, or ``Spill.decoded``): what ``Collector.snapshot`` hands the summary."""
    from ..record.columns import ColumnBuilder

    b = ColumnBuilder(sc, rows, fields, events=events, status=status, summaries=summaries)
    for ri, t in records:
        b.add(ri, t)
    return b.finish(plant_final)



class SpillRows:
    """A spill file's records (``Spill``) as rows of columns a chunk at a time, in the order of k: what the
    launcher's end-of-run summary reads (``record.summary.build_summary``), in memory bounded by the chunk
    (``CHUNK`` rows) and by how far one node's records arrived out of their own order (``role_lag``: the
    collector's ``Collector.role_lag``), not by how far the nodes fell behind one another.

    Records arrive in nearly the order of k (each node's in order, the nodes a few batches apart): after a
    record of the highest k so far, no later record has a k below that minus ``lag`` (``Collector.lag``), so
    the rows below are complete and go out as a chunk.  When a node fell behind the others by more than two
    chunks (a stalled node, a late batch: ``lag`` large, ``role_lag`` small) the file is first split into one
    unnamed file per node beside it, one pass a block at a time, and the four are read side by side a chunk of
    k at a time: the window is then two chunks and ``role_lag``.  A record out of order beyond the lag given
    raises ``RuntimeError``."""

    #: rows of a chunk
    CHUNK = 1 << 14

    def __init__(self, sc: Scenario, path: str | Path, rows: int, lag: int | None = None,
                 fields: set[str] | None = None, *, chunk: int | None = None, events: Iterable[msg.Event] = (),
                 status: Iterable[msg.AttackerStatus] = (), summaries: dict[str, dict] | None = None,
                 plant_final: msg.PlantTelemetry | None = None, top: dict[str, int] | None = None,
                 metadata: dict | None = None, role_lag: int | None = None) -> None:
        from ..record.columns import layout

        self.sc, self.path, self.fields = sc, Path(path), fields
        plant = sc.make_model()
        self.lay = layout(plant.n, plant.m, fields)
        self.rows = max(0, min(int(sc.n_steps), int(rows)))
        self.size = max(1, int(chunk or self.CHUNK))
        self.events, self.status, self.summaries = list(events), list(status), dict(summaries or {})
        self.metadata = dict(metadata or {})
        self.final: dict | None = None if plant_final is None else {"k": int(plant_final.k),
                                                       "x": np.array(plant_final.x, dtype=float),
                                                       "flow_status": int(plant_final.flow_status)}
        self._top = dict(top) if top is not None else None
        if lag is None:
            self.lag, self.role_lag = self.measure_lag()
        else:  # the collector's, counted as the records came (no role_lag: no split)
            self.lag = int(lag)
            self.role_lag = self.lag if role_lag is None else min(self.lag, int(role_lag))

    def _spill(self) -> Spill:
        sp = Spill.__new__(Spill)
        sp.path, sp.f = self.path, _NoFlush()  # type: ignore[assignment]  # the readers only flush it
        return sp

    def _blocks(self) -> Iterator[tuple[bytes, np.ndarray, np.ndarray, np.ndarray]]:
        return self._spill().blocks()

    def measure_lag(self) -> tuple[int, int]:
        """``Collector.lag`` and ``Collector.role_lag`` of the file (its k order), read from it (a spill without
        its collector)."""
        top, lag, role_lag = -1, 0, 0
        tops: dict[int, int] = {}
        for buf, ris, offs, _lens in self._blocks():
            ks = _ks(buf, offs)
            for ri in np.unique(ris):
                kr = ks[ris == ri]
                t = tops.get(int(ri), -1)
                before = np.maximum.accumulate(np.concatenate(([t], kr)))[:-1]
                role_lag = max(role_lag, int((before - kr).max()))
                tops[int(ri)] = max(t, int(kr.max()))
            before = np.maximum.accumulate(np.concatenate(([top], ks)))[:-1]  # the highest k before each record
            lag = max(lag, int((before - ks).max()))
            top = max(top, int(ks.max()))
        if self._top is None:
            self._top = {r: tops.get(i, -1) for i, r in enumerate(transport.ROLES)}
        return lag, role_lag

    def last_k(self, role: str) -> int:
        if self._top is None:
            self.measure_lag()
        assert self._top is not None  # measure_lag sets it
        return int(self._top.get(role, -1))

    def chunks(self, hi: int) -> Iterator[tuple[int, Columns]]:
        """``(k0, columns of rows k0 .. k0 + CHUNK - 1)`` covering rows 0 .. hi - 1 (at least one chunk)."""
        hi = max(0, min(int(hi), self.rows))
        try:
            if self.split:
                with contextlib.ExitStack() as files:
                    parts = self._split(files)
                    yield from self._chunks(hi, self.size + self.role_lag, self._side_by_side(parts))
            else:
                yield from self._chunks(hi, self.lag, self._blocks())
        except _Disorder as e:  # rows already handed out: the reader above starts again with every row at once
            raise RuntimeError("spill records out of order beyond the measured lag") from e

    @property
    def split(self) -> bool:
        """Whether the file is read split by node (a node behind the others by more than two chunks)."""
        return self.lag > 2 * self.size + self.role_lag

    def _split(self, files: contextlib.ExitStack) -> list[Any]:
        """The spill's records, one unnamed file per node beside it (each in the order written): one pass."""
        hs = Spill.HEAD.size
        parts = [files.enter_context(tempfile.TemporaryFile(dir=self.path.parent)) for _ in transport.ROLES]
        for buf, ris, offs, lens in self._blocks():
            arr = np.frombuffer(buf, dtype=np.uint8)
            for ri in np.unique(ris):
                sel = ris == ri
                start, n = offs[sel] - hs, lens[sel] + hs   # each record with its head
                first = np.cumsum(n) - n                   # where each lands in the node's part
                idx = np.repeat(start - first, n) + np.arange(int(n.sum()))
                parts[int(ri)].write(arr[idx].tobytes())
        for f in parts:
            f.seek(0)
        return parts

    def _side_by_side(self, parts: list[Any]) -> Iterator[tuple[bytes, np.ndarray, np.ndarray, np.ndarray]]:
        """The nodes' parts (``_split``) read side by side: each round gives every node's records up to the next
        chunk boundary of k, so a record falls behind one before it by at most a chunk and ``role_lag``."""
        streams = [_file_blocks(f, Spill.CHUNK) for f in parts]
        pending: list[tuple | None] = [None] * len(parts)
        top = [-1] * len(parts)  # each node's highest k so far
        live = list(range(len(parts)))
        bound = self.size
        while live:
            for r in list(live):
                while True:
                    if pending[r] is None:
                        nxt = next(streams[r], None)
                        if nxt is None:
                            live.remove(r)
                            break
                        buf, ris, offs, lens = nxt
                        tops = np.maximum(np.maximum.accumulate(_ks(buf, offs)), top[r])
                        top[r] = int(tops[-1])
                        pending[r] = (buf, ris, offs, lens, tops)
                    buf, ris, offs, lens, tops = pending[r]  # type: ignore[misc]  # set just above
                    j = int(np.searchsorted(tops, bound, side="left"))  # the records whose k runs below the bound
                    if j:
                        yield buf, ris[:j], offs[:j], lens[:j]
                    if j < len(tops):
                        pending[r] = (buf, ris[j:], offs[j:], lens[j:], tops[j:])
                        break
                    pending[r] = None
            bound += self.size

    def _chunks(self, hi: int, lag: int, blocks: Iterable[tuple[bytes, np.ndarray, np.ndarray, np.ndarray]]
                ) -> Iterator[tuple[int, Columns]]:
        from ..record.columns import ColumnBuilder, normalize

        size = self.size
        span = size + lag + 1
        base, top = 0, -1
        b = self._builder(span, ColumnBuilder)
        for buf, ris, offs, lens in blocks:
            ks = _ks(buf, offs)
            keep = ks < hi
            if not keep.all():
                ris, offs, lens, ks = ris[keep], offs[keep], lens[keep], ks[keep]
            if not len(ks):
                continue
            tops = np.maximum(np.maximum.accumulate(ks), top)  # the highest k up to each record
            arr = np.frombuffer(buf, dtype=np.uint8)
            i = 0
            while i < len(ks):
                # the records before the first whose k completes a chunk go in at once; that one completes it
                j = i + int(np.searchsorted(tops[i:], base + size + lag, side="left"))
                if j > i:
                    if ks[i:j].min() < base:
                        raise _Disorder(int(ks[i:j].min()))
                    _add(b, buf, arr, ris[i:j], offs[i:j], lens[i:j])
                if j < len(ks):
                    top = int(tops[j])
                    while top - lag >= base + size:  # rows below top - lag are complete
                        yield base, self._cut(b, size, normalize)
                        base += size
                        b = self._shift(b, size, span, ColumnBuilder, base)
                i = j
            top = max(top, int(tops[-1]))
        while True:
            n = min(size, hi - base)
            yield base, self._cut(b, max(0, n), normalize)
            base += size
            if base >= hi:
                return
            b = self._shift(b, size, span, ColumnBuilder, base)

    def _builder(self, span: int, ColumnBuilder: type[ColumnBuilder], k0: int = 0) -> ColumnBuilder:
        b = ColumnBuilder(self.sc, span, self.fields, summaries=self.summaries)
        b.k0 = k0
        return b

    @staticmethod
    def _cut(b: ColumnBuilder, n: int, normalize: Callable[[Columns], None]) -> Columns:
        """The first ``n`` rows of the builder's columns, as columns of their own (copies)."""
        from dataclasses import replace

        c = b.c
        out = replace(c, tables={t: v[:n].copy() for t, v in c.tables.items()}, present=c.present[:n].copy(), rows=n)
        normalize(out)
        return out

    def _shift(self, b: ColumnBuilder, size: int, span: int, ColumnBuilder: type[ColumnBuilder],
               k0: int) -> ColumnBuilder:
        """The builder's rows moved up by ``size`` (the rows after the chunk handed out), the rest fresh."""
        nb = self._builder(span, ColumnBuilder, k0)
        keep = b.c.rows - size
        if keep > 0:
            for t, v in b.c.tables.items():
                nb.c.tables[t][:keep] = v[size:]
            nb.c.present[:keep] = b.c.present[size:]
        return nb


class _Disorder(Exception):
    pass


def _ks(buf: bytes, offs: np.ndarray) -> np.ndarray:
    """The sample k of the records at ``offs`` (every telemetry record starts with it: u32 LE), as int64."""
    arr = np.frombuffer(buf, dtype=np.uint8)
    return arr[offs[:, None] + np.arange(4)].view("<u4")[:, 0].astype(np.int64)


#: the names each role's telemetry dataclass carries
_FIELDS = {ri: tuple(f.name for f in dataclasses.fields(msg.TELEMETRY_TYPES[r]))  # type: ignore[arg-type]
           for ri, r in enumerate(transport.ROLES)}


def _add(b: ColumnBuilder, buf: bytes, arr: np.ndarray, ris: np.ndarray, offs: np.ndarray, lens: np.ndarray) -> None:
    """Records into a ``ColumnBuilder``: those of one role and length at once, as one structured array
    (``columns.decode_records``); a group whose records do not share the first one's layout one by one."""
    from ..record.columns import decode_records, record_vectors

    key = ris * (1 << 32) + lens
    for g in np.unique(key):
        sel = np.flatnonzero(key == g)
        ri, n = int(ris[sel[0]]), int(lens[sel[0]])
        cls = msg.TELEMETRY_TYPES[transport.ROLES[ri]]
        vectors = record_vectors(cls, buf, int(offs[sel[0]]), n)
        rec = None if vectors is None else decode_records(cls, arr, offs[sel], vectors)
        if rec is None or vectors is None:
            for o in offs[sel]:
                b.add(ri, cls.decode(buf[o:o + n]))
        else:
            b.add_records(ri, rec, vectors, _FIELDS[ri])


class _NoFlush:
    def flush(self) -> None:
        pass
