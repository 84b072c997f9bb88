"""The launcher's collector: subscribes to a run's telemetry, events and liveliness.

Everything arrives over Zenoh as it happens, so a node killed mid-run leaves
its telemetry up to the kill.  ``snapshot(sc)`` hands it, as columns, to
``testbed.record.summary.build_summary`` (shared with ``testbed report``).

With a ``spill`` file (the launcher's: ``telemetry.bin`` in the run folder) the records are
appended there as they arrive and only the last ``RECENT`` of each node stay in memory, so that
the launcher's memory stays flat however long the run; the whole is read back once, at the end.
"""

from __future__ import annotations

import struct
import threading
import time

from ..wire import messages as msg
from ..wire import transport

PT = msg.PlantTelemetry


class Collector:
    """Telemetry, events, node summaries, start/stop and liveliness of one run."""

    #: events kept (the rest are counted): a flood cannot grow the launcher without bound
    MAX_EVENTS = 10_000
    #: records of each node kept in memory when they are spilled to a file (the stall watch reads them)
    RECENT = 1024
    _SPILL_HEAD = struct.Struct("<BI")  # role index, record length

    def __init__(self, session, keys: transport.Keys, n_steps: int, spill=None):
        import zenoh

        self._zenoh = zenoh
        self.keys = keys
        self.n_steps = int(n_steps)
        self.rejected = 0        # telemetry records for a sample outside [0, N), or a second copy of one
        self.events_dropped = 0
        self.lock = threading.Lock()
        self.tele: dict[str, dict[int, object]] = {r: {} for r in transport.ROLES}  # all, or the recent ones
        self._seen = {r: bytearray(self.n_steps // 8 + 1) for r in transport.ROLES}  # one bit per sample
        self._spill = None if spill is None else open(spill, "w+b", buffering=1 << 20)
        self.top: dict[str, int] = dict.fromkeys(transport.ROLES, -1)  # each role's highest k so far
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

    def _on_telemetry(self, sample) -> None:
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
                elif not 0 <= t.k < N or seen[t.k >> 3] & (1 << (t.k & 7)):
                    self.rejected += 1  # never stored: a k from the wire sizes nothing
                else:
                    seen[t.k >> 3] |= 1 << (t.k & 7)
                    d[t.k] = t
                    if t.k > self.top[role]:
                        self.top[role] = t.k
                    if self._spill is not None:
                        b = bytes(b)
                        self._spill.write(self._SPILL_HEAD.pack(ri, len(b)) + b)
            if self._spill is not None and len(d) > 2 * self.RECENT:
                keep = self.top[role] - self.RECENT
                for k in [k for k in d if k < keep]:
                    del d[k]

    def _on_event(self, sample) -> None:
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

    def _on_summary(self, sample) -> None:
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

    def _on_status(self, sample) -> None:
        try:
            s = msg.AttackerStatus.decode(sample.payload)
        except msg.MessageError:
            return
        with self.lock:
            if len(self.status) < self.MAX_EVENTS:
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
            if len(self.stops) < 100:
                self.stops.append(s)

    def _on_alive(self, sample) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        alive = sample.kind != self._zenoh.SampleKind.DELETE
        with self.lock:
            self.liveliness.append((time.monotonic_ns(), node, alive))
            (self.alive.add if alive else self.alive.discard)(node)

    def _on_ready(self, sample) -> None:
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

    def record(self, role: str, k: int):
        """``role``'s telemetry record of sample ``k``, or None."""
        with self.lock:
            return self.tele[role].get(k)

    def first_after(self, role: str, k: int):
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

    def event_of(self, node: str, kind: str):
        """The first event ``kind`` of ``node``, or None."""
        with self.lock:
            return next((e for e in self.events if e.node == node and e.kind == kind), None)

    def plant_done(self) -> bool:
        with self.lock:
            return any(s.origin == "plant" for s in self.stops)

    def _all_telemetry(self) -> dict[str, dict[int, object]]:
        """Every record by role and k: from the spill file when there is one (call with the lock held)."""
        if self._spill is None:
            return {r: dict(d) for r, d in self.tele.items()}
        out: dict[str, dict[int, object]] = {r: {} for r in transport.ROLES}
        f = self._spill
        f.flush()
        f.seek(0)
        head = self._SPILL_HEAD
        data = f.read()
        f.seek(0, 2)
        off = 0
        while off + head.size <= len(data):
            ri, n = head.unpack_from(data, off)
            off += head.size
            role = transport.ROLES[ri]
            t = msg.TELEMETRY_TYPES[role].decode(data[off:off + n])
            off += n
            out[role][t.k] = t
        return out

    def telemetry_check(self) -> list[dict]:
        """Each node's own account of its telemetry (records and digest, in its summary) against what
        arrived here: a difference means records were lost, forged or altered on the way."""
        import hashlib

        out = []
        with self.lock:
            tele = None
            for role in transport.ROLES:
                s = self.summaries.get(role) or {}
                if "telemetry_sha256" not in s:
                    continue
                tele = tele or self._all_telemetry()
                recs = [tele[role][k] for k in sorted(tele[role])]
                if role == "plant" and self.plant_final is not None:
                    recs.append(self.plant_final)
                h = hashlib.sha256()
                for r in recs:
                    h.update(r.encode())
                if len(recs) != s.get("telemetry_records") or h.hexdigest() != s["telemetry_sha256"]:
                    out.append({"node": role, "kind": "telemetry_mismatch",
                                "why": f"{len(recs)} records collected, the node published {s.get('telemetry_records')}"
                                       + ("" if len(recs) != s.get("telemetry_records") else "; digests differ")})
        return out

    def snapshot(self, sc):
        """What has arrived so far as columns (``testbed.record.columns.Columns``, for ``record.summary.build_summary``)."""
        from ..record.columns import from_records

        with self.lock:
            tele = self._all_telemetry()
            final, events, status, summaries = self.plant_final, list(self.events), list(self.status), \
                dict(self.summaries)
        return from_records(sc, tele, plant_final=final, events=events, status=status, summaries=summaries)
