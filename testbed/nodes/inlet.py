"""Receiving: a node's inlet of one stream, in one of the receive modes (``--rx thread|direct|spin``)."""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

# ============================================================================ receiving
#: how a node receives its control-path messages (``--rx``)
RX_MODES = ("thread", "direct", "spin")


class Inlet:
    """A node's primary input under rx mode ``spin``: a callback as usual, and a spin just before it is due.

    Each sample reaches two subscribers of the same key in the node's session: a callback
    (zenoh-python's thread, which sleeps until a sample wakes it) and a FIFO that Zenoh's
    receive thread fills without Python.  From ``margin_ns`` before the earliest arrival,
    relative to its sample instant t_k, of the last 8 samples, for at most ``budget_ns``,
    the node's thread polls the FIFO: a sample that comes then is handled at once, without
    a thread to wake; the callback's copy is then skipped (both streams hold the same
    samples in the same order, so a sample is the n-th of each).  Outside that window the
    callback handles it and drops the FIFO's copy.  One sample at a time, in order.

    ``handler(sample)`` returns the sample index k of a control message (or None): the
    arrivals teach the inlet when to spin.  ``thread``: a spinner thread of its own; else
    the node's loop calls ``window`` and ``spin`` (the plant, waiting for u_k).
    """

    HISTORY = 8

    def __init__(self, node: Any, key: str, handler: Callable[[Any], int | None], *, budget_ns: int,
                 margin_ns: int = 300_000, thread: bool = True) -> None:
        import zenoh

        self.node = node
        self.handler = handler
        self.budget_ns = int(budget_ns)
        self.margin_ns = int(margin_ns)
        self.lock = threading.Lock()
        self.n_fifo = 0       # samples taken from the FIFO
        self.n_cb = 0         # samples that reached the callback
        self.handled = 0      # the index of the next sample to handle
        self.offsets: collections.deque = collections.deque(maxlen=self.HISTORY)
        self.last_k = -1
        self.spun = 0         # samples handled while spinning
        self.woken = 0        # samples the callback handled
        self.spin_ns = 0      # time spent spinning
        self.broken = False   # the two streams differed once: the callback alone from then on
        self._seen: dict[int, bytes] = {}  # the samples the spinner handled, by index (the last 64)
        session = node.ctx.session
        self.fifo = session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024))
        self.sub = session.declare_subscriber(key, self._on_callback)
        if thread:
            threading.Thread(target=self._spinner, daemon=True, name=f"spin-{key.rsplit('/', 1)[-1]}").start()

    # ---- the two streams
    @staticmethod
    def _ident(sample: Any) -> bytes:
        att = sample.attachment
        return (b"" if att is None else att.to_bytes()) + b"|" + sample.payload.to_bytes()

    def _on_callback(self, sample: Any) -> None:
        with self.lock:
            i = self.n_cb
            self.n_cb += 1
            if self.broken:
                self._handle(sample)
                return
            mine = self._ident(sample)
            while self.n_fifo <= i:  # keep the FIFO in step: drop its copies of what the callback got
                try:
                    s = self.fifo.try_recv()
                except Exception:  # noqa: BLE001 - undeclared: the session is closing
                    s = None
                if s is None:
                    break
                if self.n_fifo == i and self._ident(s) != mine:
                    self.broken = True
                self.n_fifo += 1
            if i < self.handled and not self.broken:
                if self._seen.get(i, mine) == mine:
                    return  # the spinner had it
                self.broken = True
            if self.broken:  # the two streams differ (samples on one key from two links): no more spinning
                logging.getLogger(__name__).warning("rx spin: the two copies of a stream differ; spinning off")
                self.offsets.clear()
                self.budget_ns = 0
            self.handled = max(self.handled, i + 1)
            self.woken += 1
            self._handle(sample)

    def spin(self, until_ns: int) -> bool:
        """Poll the FIFO until a sample is handled or ``until_ns`` (run clock); True if one was."""
        import zenoh

        clock = self.node.ctx.clock
        t = time.monotonic_ns()
        try:
            while clock.now() < until_ns:
                try:
                    s = self.fifo.try_recv()
                except zenoh.ZError:  # undeclared: the session is closing
                    return False
                if s is None:
                    os.sched_yield()  # releases the GIL and lets this CPU's other threads (Zenoh's) run
                    continue
                with self.lock:
                    if self.broken:
                        return False
                    i = self.n_fifo
                    self.n_fifo += 1
                    if i < self.handled:
                        continue  # the callback had it
                    self.handled = i + 1
                    self.spun += 1
                    self._seen[i] = self._ident(s)
                    self._seen.pop(i - 64, None)
                    self._handle(s)
                return True
            return False
        finally:
            self.spin_ns += time.monotonic_ns() - t

    def _handle(self, sample: Any) -> None:
        ctx = self.node.ctx
        clock = ctx.clock
        rx = clock.now() if clock is not None else None
        k = self.handler(sample)
        if k is not None and rx is not None and k > self.last_k:
            self.last_k = k
            self.offsets.append(rx - k * ctx.T_ns)

    # ---- when to spin
    def window(self, now: int) -> tuple[int, int] | None:
        """(start, end) of the spin window of the next sample due, in run-clock ns, or None."""
        if not self.offsets or self.budget_ns <= 0:
            return None
        T_ns = self.node.ctx.T_ns
        lead = min(self.offsets) - self.margin_ns
        j = max(self.last_k + 1, -(-(now - lead - self.budget_ns) // T_ns))
        start = j * T_ns + lead
        return start, start + self.budget_ns

    def _spinner(self) -> None:
        ctx = self.node.ctx
        stop = ctx.stop
        while not stop.is_set():
            clock = ctx.clock
            now = clock.now() if clock is not None else 0
            w = self.window(now) if clock is not None else None
            if w is None:
                stop.wait(0.05)
                continue
            if now < w[0]:
                stop.wait(min((w[0] - now) / 1e9, 0.05))
                continue
            j = (w[0] - min(self.offsets) + self.margin_ns) // ctx.T_ns
            if not self.spin(w[1]):  # nothing in this window: no second one for this sample
                with self.lock:
                    self.last_k = max(self.last_k, j)

    def stats(self) -> dict:
        return {"spun": self.spun, "woken": self.woken, "spin_ms": round(self.spin_ns / 1e6, 3)}


