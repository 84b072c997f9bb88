"""``testbed run --foxglove [PORT]``: the run served live over Foxglove's WebSocket protocol.

The launcher subscribes to the run's telemetry, events, attacker status and
start / stop over Zenoh (like the recorder, off the control loop's path: the
Zenoh callbacks only append the raw bytes to a deque), and a daemon thread at
nice 10 decodes them and logs them through ``foxglove-sdk``'s WebSocket server
on loopback: the telemetry channels with the recording's own protobuf schemas
(with ``header.stamp`` and ``log10_E``), and ``/log``, ``/phase``,
``/phase/roa`` from the same ``FoxgloveTopics`` tap the recorder uses, so the
live view and a recording opened later show the same topics and layout
(``docs/foxglove-layout.json``).  Open Foxglove and connect to
``ws://127.0.0.1:PORT`` (default 8765).
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from typing import TYPE_CHECKING, Any

from ..common.errors import BadInput
from ..record import schema, topics
from ..view.foxglove import TOPICS as FOXGLOVE_TOPICS
from ..view.foxglove import FoxgloveTopics, descriptor_set, telemetry_extra
from ..wire import messages as msg
from ..wire.transport import Keys

if TYPE_CHECKING:
    import foxglove

log = logging.getLogger("testbed.launcher")
NICE = 10


class FoxgloveLive:
    """A foxglove-sdk WebSocket server fed from the run's Zenoh keys by a background thread."""

    def __init__(self, sc, run_id: str, port: int, *, host: str = "127.0.0.1"):
        try:
            import foxglove
        except ImportError:
            raise BadInput("--foxglove needs foxglove-sdk: pip install 'dos-testbed[foxglove]'") from None
        self._fg = foxglove
        self.sc, self.run_id, self.port, self.host = sc, run_id, int(port), host
        self.T_ns = int(round(sc.T * 1e9))
        self.tap = FoxgloveTopics(sc, background=True)
        self.q: collections.deque = collections.deque()
        self.server: foxglove.WebSocketServer | None = None
        self.channels: dict[str, foxglove.Channel] = {}
        self.logged = 0
        self.errors = 0
        self._subs: list = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _schema(self, name: str):
        if "." in name:
            return self._fg.Schema(name=name, encoding="protobuf", data=descriptor_set(name))
        return self._fg.Schema(name=schema.full_name(name), encoding="protobuf", data=schema.file_descriptor_set())

    def start(self, session: Any, keys: Keys) -> None:
        """Declare every channel, start the server (loopback), subscribe to the run's keys.

        The channels exist before the server does, so a viewer that connects at once gets them all in
        its first advertisement.  (foxglove-sdk advertises a channel created while a viewer is
        connected before it records the channel as advertised; a viewer fast enough to subscribe in
        between is told "Unknown channel ID" and never gets that topic.)
        """
        table = {**{t: n for t, n in ((topics.TELEMETRY_TOPICS[r], topics.TELEMETRY_SCHEMA[r])
                                      for r in topics.TELEMETRY_TOPICS)}, **FOXGLOVE_TOPICS}
        for topic, name in table.items():
            self.channels[topic] = self._fg.Channel(topic, message_encoding="protobuf", schema=self._schema(name))
        try:
            self.server = server = self._fg.start_server(name=f"testbed {self.run_id}", host=self.host, port=self.port)
        except Exception as e:  # noqa: BLE001 - a port in use, mostly
            raise BadInput(f"--foxglove {self.port}: cannot serve on {self.host}:{self.port} ({e})") from None
        self.port = server.port
        p = keys.prefix
        self._plen = len(p) + 1
        for k in (f"{p}/telemetry/*", f"{p}/events/*", keys.attacker_status, keys.start, keys.stop):
            self._subs.append(session.declare_subscriber(k, self._on_sample))
        self._thread = threading.Thread(target=self._loop, name="foxglove-live", daemon=True)
        self._thread.start()

    def _on_sample(self, sample) -> None:  # a Zenoh thread: just enqueue
        self.q.append((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    # ---- the background thread
    def _loop(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
        except OSError:
            pass
        while True:
            stopping = self._stop.is_set()
            while self.q:
                key, payload, t = self.q.popleft()
                try:
                    self._handle(key[self._plen:], payload, t)
                except Exception:  # noqa: BLE001 - a bad message never stops the view
                    self.errors += 1
            if stopping:
                break
            self._stop.wait(0.02)
        self._emit(self.tap.flush(time.time_ns()))

    def _emit(self, items) -> None:
        for topic, _name, data, lt in items:
            self.channels[topic].log(data, log_time=lt)
            self.logged += 1

    def _handle(self, rel: str, payload: bytes, t: int) -> None:
        tap = self.tap
        if rel.startswith("telemetry/"):
            role = rel[len("telemetry/"):]
            typ = msg.TELEMETRY_TYPES.get(role)
            if typ is None:
                return
            name = topics.TELEMETRY_SCHEMA[role]
            ch = self.channels[topics.TELEMETRY_TOPICS[role]]
            for r in msg.unpack_batch(payload):
                m = typ.decode(r)
                if not 0 <= m.k <= tap.N:
                    continue
                data = schema.to_pb(m, name, telemetry_extra(name, m, tap.t0, self.T_ns)).SerializeToString()
                ch.log(data, log_time=t)
                self.logged += 1
                if role in ("plant", "encoder"):
                    self._emit(getattr(tap, role)(m, t))
        elif rel.startswith("events/"):
            self._emit(tap.event(msg.Event.decode(payload), t))
        elif rel == "attacker/status":
            self._emit(tap.status(msg.AttackerStatus.decode(payload), t))
        elif rel == "control/start":
            self._emit(tap.start(msg.Start.decode(payload), t))
        elif rel == "control/stop":
            self._emit(tap.stop(msg.Stop.decode(payload), t))

    def finish(self, linger: float = 0.0) -> None:
        """Stop taking messages, log what is queued, stop the server (after ``linger`` s for late viewers)."""
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)
        if linger > 0:
            time.sleep(linger)
        if self.server is not None:
            self.server.stop()
            self.server = None

    def info(self) -> dict:
        return {"url": f"ws://{self.host}:{self.port}", "messages": self.logged, "errors": self.errors}


__all__ = ["FoxgloveLive"]
