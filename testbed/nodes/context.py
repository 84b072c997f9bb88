"""A node's context: its session, publishers and subscribers, its telemetry and the roles it hosts."""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from ..wire import messages as msg
from ..wire import transport
from .clock import CLOCK_TOLERANCE_NS, RunClock
from .options import RunOptions, T_ns, run_digest

log = logging.getLogger("testbed.nodes")


# ============================================================================ node context
class NodeContext:
    """A node's session, keys, liveliness view, event log and run clock."""

    def __init__(self, role: str, session, sc, opts: RunOptions, keys: transport.Keys):
        import zenoh

        self._zenoh = zenoh  # first: liveliness callbacks (history=True) may fire during __init__
        self.role = role
        self.session = session
        self.sc = sc
        self.opts = opts
        self.keys = keys
        self.digest = run_digest(sc, opts)
        self.T_ns = T_ns(sc)
        self.n_steps = sc.n_steps
        self.clock_tolerance_ns = CLOCK_TOLERANCE_NS
        self.stop = threading.Event()
        self.stop_reason = ""
        self.start_msg: msg.Start | None = None
        self.protocol_refused: str | None = None  # a Start of another protocol version: why this node refused
        self.clock: RunClock | None = None
        self._start_ev = threading.Event()
        self._lock = threading.Lock()
        self.alive: set[str] = set()
        self.ready: set[str] = set()
        self._peer_handlers: list = []
        self._cond = threading.Condition()
        self.events_sent = 0
        self.events_suppressed = 0
        self._ev_window: dict[str, tuple[float, int]] = {}
        self._ev_lock = threading.Lock()
        self._ev_pub = session.declare_publisher(keys.events(role), **transport.telemetry_qos())
        self.telemetry = TelemetryOut(session.declare_publisher(keys.telemetry(role), **transport.telemetry_qos()),
                                      self.T_ns, background=True)
        self._subs = [
            session.declare_subscriber(keys.start, self._on_start),
            session.declare_subscriber(keys.stop, self._on_stop),
            session.liveliness().declare_subscriber(keys.alive("*"), self._on_alive, history=True),
            session.liveliness().declare_subscriber(keys.ready("*"), self._on_ready, history=True),
        ]
        self._tokens: list = []
        self.watch_collector = False  # launched by ``testbed run``: stop when the launcher goes away

    # ---- liveliness
    def _on_alive(self, sample) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        gone = sample.kind == self._zenoh.SampleKind.DELETE
        with self._cond:
            if gone:
                self.alive.discard(node)
            else:
                self.alive.add(node)
            self._cond.notify_all()
        if gone and node == transport.COLLECTOR and self.watch_collector:
            self.request_stop("launcher lost")
        for h in self._peer_handlers:
            try:
                h(node, not gone)
            except Exception:
                log.exception("peer handler failed")

    def _on_ready(self, sample) -> None:
        node = transport.Keys.node_of(sample.key_expr)
        with self._cond:
            if sample.kind == self._zenoh.SampleKind.DELETE:
                self.ready.discard(node)
            else:
                self.ready.add(node)
            self._cond.notify_all()

    def on_peer(self, handler: Callable[[str, bool], None]) -> None:
        """``handler(node, alive: bool)`` on every liveliness change (runs on a Zenoh thread)."""
        self._peer_handlers.append(handler)

    def declare_alive(self) -> None:
        self._tokens.append(self.session.liveliness().declare_token(self.keys.alive(self.role)))

    def declare_ready(self) -> None:
        self._tokens.append(self.session.liveliness().declare_token(self.keys.ready(self.role)))

    def wait_for(self, what: str, nodes: Iterable[str], timeout: float) -> bool:
        """Wait until every node of ``nodes`` is in ``self.alive`` / ``self.ready``."""
        want = set(nodes)
        end = time.monotonic() + timeout
        with self._cond:
            while not want <= getattr(self, what):
                rem = end - time.monotonic()
                if rem <= 0 or self.stop.is_set():
                    return False
                self._cond.wait(min(rem, 0.1))
        return True

    def missing(self, what: str, nodes: Iterable[str]) -> list[str]:
        with self._cond:
            return sorted(set(nodes) - getattr(self, what))

    # ---- start / stop
    def _on_start(self, sample) -> None:
        try:
            st = msg.Start.decode(sample.payload)
        except msg.ProtocolMismatch as e:
            with self._lock:
                if self.start_msg is not None or self.protocol_refused is not None:
                    return
                self.protocol_refused = str(e)
            self.event("protocol_mismatch", detail=str(e), level=logging.INFO)  # main prints the one line
            self.request_stop("protocol mismatch")
            return
        except msg.MessageError as e:
            self.event("bad_start", detail=str(e))
            return
        with self._lock:
            if self.start_msg is not None:
                return
            if st.digest != self.digest:
                self.event("run_mismatch", detail=f"start digest {st.digest} != mine {self.digest}: "
                                                  "different scenario or run options")
                self.request_stop("run mismatch")
                return
            self.start_msg = st
            self.clock = RunClock(st.t0_ns)
        self._start_ev.set()

    #: who may stop a run (the access control of the router topology enforces it as well)
    STOP_ORIGINS = ("plant", "launcher")

    def _on_stop(self, sample) -> None:
        try:
            s = msg.Stop.decode(sample.payload)
        except msg.MessageError as e:
            self.event("stop_rejected", detail=f"malformed stop message: {e}")
            return
        if s.origin not in self.STOP_ORIGINS:
            self.event("stop_rejected", detail=f"stop from {s.origin!r}: only the plant or the launcher stops a run")
            return
        self.request_stop(f"stop from {s.origin}: {s.reason}")

    def request_stop(self, reason: str) -> None:
        if not self.stop.is_set():
            self.stop_reason = reason
            self.stop.set()
        self._start_ev.set()
        with self._cond:
            self._cond.notify_all()

    def wait_start(self, timeout: float) -> msg.Start | None:
        self._start_ev.wait(timeout)
        return self.start_msg if not self.stop.is_set() else None

    def wait_clock(self, timeout: float = 1.0) -> RunClock | None:
        """The run clock, waiting up to ``timeout`` for the Start (a control message may overtake it)."""
        if self.clock is None:
            self._start_ev.wait(timeout)
        return self.clock

    def adopt_start(self, st: msg.Start) -> None:
        """The plant chose t0 itself."""
        with self._lock:
            self.start_msg = st
            self.clock = RunClock(st.t0_ns)
        self._start_ev.set()

    def now(self) -> int:
        return self.clock.now() if self.clock else msg.NO_TIME

    def newest_k(self, now_ns: int) -> int:
        """The newest sample whose instant t_k = k T has come at ``now_ns`` (run clock), within the
        clock tolerance: a message for a later sample cannot be genuine."""
        return (now_ns + self.clock_tolerance_ns) // self.T_ns

    @property
    def end_ns(self) -> int:
        """ns since t0 after which nothing of the run can still happen."""
        return self.n_steps * self.T_ns

    # ---- events
    EVENTS_PER_SECOND = 20  # per kind; the rest are only counted (``events_suppressed``)

    def event(self, kind: str, k: int = -1, detail: str = "", level: int = logging.WARNING) -> None:
        """Log and publish an event, at most EVENTS_PER_SECOND of each kind per second."""
        now = time.monotonic()
        with self._ev_lock:
            t_win, n = self._ev_window.get(kind, (now, 0))
            if now - t_win >= 1.0:
                t_win, n = now, 0
            if n >= self.EVENTS_PER_SECOND:
                self.events_suppressed += 1
                self._ev_window[kind] = (t_win, n)
                return
            self._ev_window[kind] = (t_win, n + 1)
        e = msg.Event(node=self.role, kind=kind, k=int(k), t_ns=self.now(), detail=detail)
        log.log(level, "%s: %s k=%d %s", self.role, kind, k, detail)
        self.events_sent += 1
        try:
            self._ev_pub.put(e.encode())
        except Exception:  # noqa: BLE001 - the session may be closing
            pass

    def publish_summary(self, data: dict) -> None:
        s = msg.NodeSummary(node=self.role, data=data)
        try:
            self.session.put(self.keys.summary(self.role), s.encode(),
                             congestion_control=self._zenoh.CongestionControl.BLOCK)
        except Exception:
            log.exception("summary not published")

    #: how long a node waits at exit for the collector to hold its summary (``summary_received``)
    RECEIPT_TIMEOUT_S = 2.0

    def summary_received(self, roles: Iterable[str], timeout: float = RECEIPT_TIMEOUT_S) -> bool:
        """Whether the launcher's collector holds the summaries of ``roles``: asked on ``collector/summaries``
        until it does, at most ``timeout`` s.  A session closed right after its last put can lose it (the
        router still had messages for this node, whose close then resets the link before the router has
        read the summary); the query goes behind the summary on the same link (the same priority), so its
        reply comes after the summary reached the collector."""
        want, end = set(roles), time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0 and transport.COLLECTOR in self.alive:
            try:
                replies = list(self.session.get(self.keys.summaries_held, timeout=left))
            except Exception:  # noqa: BLE001 - the session is closing: nothing more to wait for
                return False
            if any(want <= _roles_held(r) for r in replies):
                return True
            time.sleep(0.02)
        if transport.COLLECTOR not in self.alive:
            return False  # the launcher is gone: nobody to confirm
        log.warning("%s: the collector did not confirm the summaries of %s in %g s", self.role, sorted(want), timeout)
        return False

    def close(self) -> None:
        for t in self._tokens:
            try:
                t.undeclare()
            except Exception:  # noqa: BLE001 - leaving: a token the session already dropped
                pass


class TelemetryOut:
    """Per-sample telemetry records, published in batches of at most ~``max_delay`` worth of samples.

    One record per message at T = 0.1 s; at T = 1 ms 20 records every 20 ms, so the
    per-message cost of Zenoh and of the readers stays off the control loop.  The batches
    are published by a thread of their own, not by the thread that sent the control
    message, and at T >= 10 ms half a period (at most 20 ms) after the record, when the
    loop's messages of that sample have long gone (``quiet_ns``).  ``immediate``: publish
    each batch at once from the caller (a reader waits for it: the greedy attacker's
    score E_k).  A node killed mid-run loses at most one batch.
    """

    def __init__(self, pub, T_ns: int, max_delay_ns: int = 20_000_000, *, background: bool = True):
        self.pub = pub
        self.n = int(max(1, min(64, max_delay_ns // max(T_ns, 1))))
        self.buf: list[bytes] = []
        self.lock = threading.Lock()
        # testbed run --rerun: a deque's append (testbed.nodes.rerun_tap), nothing more
        self.tap: Callable[[bytes], None] | None = None
        self._digest = hashlib.sha256()  # of every record, in order: the launcher checks what it received
        self.records = 0
        self.immediate = not background
        self.quiet_ns = min(T_ns // 2, max_delay_ns) if T_ns >= 10_000_000 else 0
        self._queue: list[tuple[int, bytes]] = []   # (monotonic ns due, batch) for the publisher thread
        self._cv = threading.Condition(self.lock)
        self._pub_lock = threading.Lock()           # one publisher at a time, batches in order
        self._thread: threading.Thread | None = None
        self._closed = False

    def digest(self) -> dict:
        """The node's own account of its telemetry (it goes into its summary)."""
        with self.lock:
            return {"telemetry_records": self.records, "telemetry_sha256": self._digest.hexdigest()}

    def put(self, record: bytes) -> None:
        tap = self.tap
        if tap is not None:
            tap(record)
        with self.lock:
            if self._closed:
                return
            self._digest.update(record)
            self.records += 1
            self.buf.append(record)
            if len(self.buf) < self.n:
                return
            data = msg.pack_batch(self.buf)
            self.buf.clear()
            if not self.immediate:
                self._queue.append((time.monotonic_ns() + self.quiet_ns, data))
                if self._thread is None:
                    self._thread = threading.Thread(target=self._publisher, daemon=True, name="telemetry")
                    self._thread.start()
                self._cv.notify()
                return
        self._publish(data)

    def _publish(self, data: bytes) -> None:
        with self._pub_lock:
            try:
                self.pub.put(data)
            except Exception:  # noqa: BLE001 - the session may be closing
                pass

    def _publisher(self) -> None:
        while True:
            with self._cv:
                while not self._queue:
                    self._cv.wait()
                due = self._queue[0][0]
            rem = due - time.monotonic_ns()
            if rem > 0:
                time.sleep(rem / 1e9)
            with self._pub_lock:
                with self.lock:
                    if not self._queue:
                        continue
                    _due, data = self._queue.pop(0)
                try:
                    self.pub.put(data)
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass

    def flush(self) -> None:
        """Publish everything now (from the caller), queued batches first."""
        with self._pub_lock:
            with self.lock:
                batches = [d for _due, d in self._queue]
                self._queue.clear()
                if self.buf:
                    batches.append(msg.pack_batch(self.buf))
                    self.buf.clear()
            for data in batches:
                try:
                    self.pub.put(data)
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass

    def discard(self) -> None:
        """Drop what is not published yet and publish nothing more (a colocated role that died)."""
        with self.lock:
            self._closed = True
            self._queue.clear()
            self.buf.clear()


class RoleView:
    """Another role's face on a node's context: a role run inside this node's process (``--colocate``).

    It has its own name, telemetry, events, summary and liveliness tokens (so readers see
    the role as if it were a process of its own); everything else (session, clock, stop,
    peers) is the host node's.
    """

    def __init__(self, ctx: "NodeContext", role: str):
        self._ctx = ctx
        self.role = role
        self.events_sent = 0
        self.events_suppressed = 0
        self._ev_window: dict[str, tuple[float, int]] = {}
        self._ev_lock = threading.Lock()
        self._ev_pub = ctx.session.declare_publisher(ctx.keys.events(role), **transport.telemetry_qos())
        self.telemetry = TelemetryOut(ctx.session.declare_publisher(ctx.keys.telemetry(role),
                                                                    **transport.telemetry_qos()), ctx.T_ns,
                                      background=True)
        self._tokens: list = []

    def __getattr__(self, name):
        return getattr(self._ctx, name)

    event = NodeContext.event
    publish_summary = NodeContext.publish_summary
    declare_alive = NodeContext.declare_alive
    declare_ready = NodeContext.declare_ready
    close = NodeContext.close


def warm_publisher(pub: Any, payload: bytes, times: int = 3, pause: float = 0.001) -> None:
    """First puts on a publisher are slow: send a few with the warm-up index (readers ignore them)."""
    att = msg.Header(msg.WARMUP_K, 0).encode()
    for _ in range(times):
        pub.put(payload, attachment=att)
        time.sleep(pause)


def _roles_held(reply: Any, limit: int = 1024) -> set[str]:
    """The roles of a ``collector/summaries`` reply (a JSON list of names); anything else: none."""
    ok = getattr(reply, "ok", None)
    raw = b"" if ok is None else ok.payload.to_bytes()
    try:
        held = json.loads(raw) if len(raw) <= limit else None
    except ValueError:
        return set()
    return {r for r in held if isinstance(r, str)} if isinstance(held, list) else set()
