"""No silent waits: a numba compilation that takes longer than a second says what it compiles.

numba compiles a kernel the first time it is called with new types, and caches the result on
disk (``__pycache__`` beside the source; the specialized batch kernel in
``$TESTBED_CACHE_DIR/kernels``). A first run of a new plant therefore waits tens of seconds
once. :func:`install` listens to numba's ``numba:compile`` events (sent only for real
compilations, not for kernels loaded from the cache): when one is still running after
``DELAY`` seconds, one line on stderr names the kernel and says that this happens once; when the
outermost compilation ends, a second line gives the time it took.

Installing imports numba, so the commands that compute call it (``testbed.cli``, the API's
``testbed.simulate`` and ``testbed.open``), not ``import testbed``.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import TextIO

#: seconds a compilation may take silently
DELAY = 1.0

_installed = False


def _describe(dispatcher) -> str:
    py = getattr(dispatcher, "py_func", None)
    if py is None:
        return "a numba kernel"
    mod = getattr(py, "__module__", "") or ""
    if mod.startswith("_testbed_kernel_"):  # testbed.sim.kernelcache's module for one plant
        return f"the batch simulator for this plant ({py.__qualname__}, testbed.sim.kernelcache)"
    return f"{mod}.{py.__qualname__}" if mod else py.__qualname__


class _Notice:
    """The numba listener: one line after ``delay`` s of compiling, one when it is done."""

    def __init__(self, stream=None, delay: float = DELAY):
        self.stream = stream
        self.delay = delay
        self.depth = 0
        self.t0 = 0.0
        self.timer: threading.Timer | None = None
        self.said = False
        self.lock = threading.Lock()

    def _out(self):
        return self.stream if self.stream is not None else sys.stderr

    def _say(self, what: str) -> None:
        with self.lock:
            if self.depth == 0 or self.said:
                return
            self.said = True
        print(f"testbed: compiling {what} with numba (this happens once: the result is cached on disk for "
              "the next runs) ...", file=self._out(), flush=True)

    def start(self, dispatcher) -> None:
        with self.lock:
            self.depth += 1
            if self.depth > 1:
                return
            self.t0 = time.perf_counter()
            self.said = False
            if self.delay > 0:
                self.timer = threading.Timer(self.delay, self._say, args=(_describe(dispatcher),))
                self.timer.daemon = True
                self.timer.start()
        if self.delay <= 0:
            self._say(_describe(dispatcher))

    def end(self) -> None:
        with self.lock:
            self.depth = max(self.depth - 1, 0)
            if self.depth:
                return
            timer, self.timer = self.timer, None
        if timer is not None:
            # gone before the caller goes on: the analysis forks its workers only when it runs one thread
            timer.cancel()
            timer.join()
        with self.lock:
            said = self.said
        if said:
            print(f"testbed: compiled in {time.perf_counter() - self.t0:.1f} s", file=self._out(), flush=True)


def install(stream: TextIO | None = None, delay: float = DELAY) -> None:
    """Listen to numba's compilations in this process (once; later calls do nothing)."""
    global _installed
    if _installed:
        return
    from numba.core import event

    notice = _Notice(stream, delay)

    class _Listener(event.Listener):
        def on_start(self, ev):
            notice.start((ev.data or {}).get("dispatcher"))

        def on_end(self, ev):
            notice.end()

    event.register("numba:compile", _Listener())
    _installed = True


__all__ = ["install", "DELAY"]
