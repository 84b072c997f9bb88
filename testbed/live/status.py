"""A live run shows that it is alive: one status line on stderr, updated about once a second.

On a terminal (stderr a tty) the line is redrawn in place; on a pipe nothing is written unless
``testbed run --progress`` asks for it, and then each update is a line of its own.  Nothing goes to
stdout.  ``status_text`` formats the line; ``LiveStatus`` counts what the collector
(``testbed.live.collect``) received as it arrives, each record once, in bounded memory: samples
lost by cause (``testbed.loop.channel.recorded_losses``, the function the run's summary uses), the
plant's deadline misses, and the last E_k at the encoder and at the controller (the decoder).
"""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from ..loop.channel import LOSS_KINDS, NetworkModel, late_of_rest, loss_text, model_lost, recorded_losses
from ..wire import messages as msg

if TYPE_CHECKING:
    from .collect import Collector

PT = msg.PlantTelemetry
CT = msg.ControllerTelemetry

#: seconds between two updates of the line
INTERVAL_S = 1.0


def status_text(k: int, N: int, losses: dict, misses: int, E_enc: float | None, E_dec: float | None) -> str:
    """``sample k/N | lost L (attacker a, channel c, network n, late l, withheld w) | deadline misses m | E_k enc e, dec d``:
    ``k`` the plant's latest sample (1-based count of samples taken), ``losses`` a ``recorded_losses`` dict."""
    lost = sum(losses.values())
    causes = loss_text(losses)

    def e(v: float | None) -> str:
        return "-" if v is None else f"{v:.3g}"

    return (f"sample {k}/{N} | lost {lost} ({causes}) | deadline misses {misses} | "
            f"E_k enc {e(E_enc)}, dec {e(E_dec)}")


class LiveStatus:
    """The status line of one run: ``tick(col)`` as often as the launcher watches (it reads only the records
    that came since the last call), a redraw at most every ``INTERVAL_S``; ``close()`` at the end."""

    #: a sample's cause is decided once the plant is this many periods past it (its encoder's, attacker's
    #: and controller's records have come by then), or at the end
    LAG_S = 0.1

    def __init__(self, n_steps: int, T_s: float, stream: TextIO | None = None, *, tty: bool | None = None,
                 network: NetworkModel | None = None) -> None:
        self.N = int(n_steps)
        self.channel_lost = model_lost(network, self.N + 2)  # the [network] model's decisions, known ahead
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(self.stream.isatty()) if tty is None else tty
        self.lag = max(2, int(np.ceil(self.LAG_S / T_s)))
        self.next_plant = 0          # the plant's next record to read
        self.next_loss = 0           # the next sample whose loss is decided
        self.misses = 0
        self.losses = dict.fromkeys(LOSS_KINDS, 0)
        self.E_enc: float | None = None
        self.E_dec: float | None = None
        self.k = 0                   # samples the plant has taken
        self._last = 0.0
        self._shown = False

    # ---- counting
    def _count(self, col: Collector, final: bool) -> None:
        top = col.last_k("plant")
        for j in range(self.next_plant, top + 1):
            r = col.record("plant", j)
            if r is not None and r.flags & PT.FLAG_MISS:
                self.misses += 1
        self.next_plant = max(self.next_plant, top + 1)
        self.k = top + 1
        upto = col.last_k("controller") if final else min(col.last_k("controller"), top - self.lag)
        ks = range(self.next_loss, upto + 1)
        if len(ks):
            rec = [(col.record("controller", j), col.record("encoder", j), col.record("attacker", j)) for j in ks]
            theta = np.array([c is not None and c.theta != 0 for c, _, _ in rec])
            reason = np.array([c.reason if c is not None else -1 for c, _, _ in rec])
            got = recorded_losses(theta, withheld=[e is not None and bool(e.silent) for _, e, _ in rec],
                                  attacker=[a is not None and bool(a.dropped) for _, _, a in rec],
                                  invalid=reason == CT.INVALID, superseded=reason == CT.SUPERSEDED, late_symbols=0,
                                  channel_lost=self.channel_lost[ks.start:ks.stop])
            for c, n in got.items():
                self.losses[c] = self.losses.get(c, 0) + n
            self.next_loss = upto + 1
        e = col.record("encoder", col.last_k("encoder"))
        if e is not None and not e.silent:
            self.E_enc = float(e.E)
        c = col.record("controller", col.last_k("controller"))
        if c is not None:
            self.E_dec = float(c.E)

    # ---- drawing
    def line(self) -> str:
        return status_text(self.k, self.N, self.losses, self.misses, self.E_enc, self.E_dec)

    def _draw(self) -> None:
        if self.tty:
            self.stream.write("\r\x1b[K" + self.line())
            self._shown = True
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()

    def clear(self) -> None:
        """Take the line off the terminal (before another line is written to stderr)."""
        if self._shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self._shown = False

    def tick(self, col: Collector, now: float | None = None) -> None:
        """Count what came since the last call (every call: the collector keeps only its last ``RECENT``
        records of a node, so a fast loop is counted as it goes), and redraw once ``INTERVAL_S`` has passed."""
        self._count(col, final=False)
        now = time.monotonic() if now is None else now
        if now - self._last < INTERVAL_S:
            return
        self._last = now
        self._draw()

    def close(self, col: Collector | None = None) -> None:
        """The last state, counted to the end, as a line of its own (the terminal's line ends there).  Its
        losses are the run's ``losses``: the controller's count of late symbols (its summary) moves that many
        of the real network's to late, as ``recorded_losses`` does."""
        if col is not None:
            self._count(col, final=True)
            late = (col.snapshot_summaries().get("controller") or {}).get("late")
            m = late_of_rest(self.losses["network"], late)
            self.losses["network"] -= m
            self.losses["late"] += m
            self._draw()
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()
            self._shown = False


class ClearingStream:
    """``sys.stderr`` while a terminal's status line is up: any other write takes the line off first, so
    that the launcher's own stderr lines (a node lost, a stall) never land in the middle of it."""

    def __init__(self, stream: TextIO, status: LiveStatus) -> None:
        self._stream, self._status = stream, status

    def write(self, s: str) -> int:
        if s:
            self._status.clear()
        return self._stream.write(s)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def start(progress: bool, n_steps: int, T_s: float, network: NetworkModel | None = None) -> LiveStatus | None:
    """The run's status line on stderr: on a terminal, or on a pipe with ``progress``; None otherwise.
    On a terminal ``sys.stderr`` becomes a ``ClearingStream`` until ``stop``."""
    real = sys.stderr
    try:
        tty = bool(real.isatty())
    except (AttributeError, ValueError):
        tty = False
    if not (tty or progress):
        return None
    st = LiveStatus(n_steps, T_s, real, tty=tty, network=network)
    if tty:
        sys.stderr = ClearingStream(real, st)
    return st


def stop(st: LiveStatus | None, col: Collector) -> None:
    """The last status line (counted to the end), and stderr back as it was."""
    if st is None:
        return
    if isinstance(sys.stderr, ClearingStream) and sys.stderr._status is st:
        sys.stderr = st.stream
    st.close(col)


__all__ = ["INTERVAL_S", "ClearingStream", "LiveStatus", "start", "status_text", "stop"]
