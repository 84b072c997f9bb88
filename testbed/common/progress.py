"""The progress bar of every long command (``testbed analyze``, ``search``, ``noise``, ``campaign``), on
stderr only.  On a terminal it is tqdm's bar, drawn in place, with its estimate of the time left from
a smoothed rate; on a pipe or a file (a log, CI) no bar is drawn but a plain line now and then, as a
log wants: :class:`Progress` a line per tenth of the work, :class:`RunsProgress` (a campaign's runs)
a line every 5 s.  Nothing goes to stdout, which holds a command's result (``--json``)."""

from __future__ import annotations

import sys
import time

from tqdm import tqdm


def is_tty() -> bool:
    """Whether stderr is a terminal (where a bar is drawn in place)."""
    return sys.stderr.isatty()


def bar(label: str, total: int, *, initial: int = 0, unit: str = "it") -> tqdm:
    """A tqdm bar on stderr (a terminal): ``label``, done of ``total``, elapsed and the time left."""
    return tqdm(total=total, initial=initial, desc=label, unit=unit, file=sys.stderr, dynamic_ncols=True,
                mininterval=0.2, leave=True)


def say(text: str) -> None:
    """One line on stderr, above a bar drawn in place (tqdm redraws the bar below it)."""
    tqdm.write(text, file=sys.stderr)
    sys.stderr.flush()


class Progress:
    """The progress of ``done`` of ``total`` steps of one piece of work (``label``): called as
    ``progress(done, total)``.  Off a terminal: ``label [#####     ] done/total  el s, ETA s`` once per
    tenth of the work and at its end."""

    def __init__(self, label: str, enabled: bool = True, width: int = 30):
        self.label = label
        self.enabled = enabled
        self.width = width
        self.t0 = time.perf_counter()
        self.tty = is_tty()
        self._last_pct = -1
        self._bar: tqdm | None = None

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or total <= 0:
            return
        if self.tty:
            if self._bar is None:
                self._bar = bar(self.label, total)
            b = self._bar
            if b.total != total:
                b.total = total
            b.update(done - b.n)
            if done >= total:
                b.close()
                self._bar = None
            return
        frac = done / total
        pct = int(frac * 10)
        if pct == self._last_pct and done < total:
            return
        self._last_pct = pct
        el = time.perf_counter() - self.t0
        eta = el / frac * (1 - frac) if frac > 0 else float("nan")
        hashes = "#" * int(round(frac * self.width))
        sys.stderr.write(f"{self.label} [{hashes:<{self.width}}] {done}/{total} {el:6.1f} s"
                         + (f", ETA {eta:5.1f} s" if done < total else "") + "\n")
        sys.stderr.flush()


class RunsProgress:
    """What a campaign does, on stderr: the setup's steps (:meth:`say`), then runs done, failed and left
    and an estimate of the time left.  The estimate starts at the first run's end (that run loads or
    compiles the simulator, which the others do not pay): on a terminal the bar starts there, off one
    the estimate is shown once a run more has ended."""

    def __init__(self, total: int, done: int, enabled: bool = True, label: str = "campaign"):
        self.total, self.done0, self.enabled, self.label = total, done, enabled, label
        self.t0 = time.perf_counter()
        self.tty = is_tty()
        self.last = 0.0
        self.shown: tuple[int, int] | None = None
        self.clock: tuple[float, int] | None = None  # (time, runs done) at the end of the first run: where the estimate starts
        self._bar: tqdm | None = None

    def say(self, text: str) -> None:
        """One line of what the campaign is doing (the setup), on stderr."""
        if self.enabled:
            say(f"{self.label}: {text}")

    def eta(self, done: int, now: float) -> float | None:
        """Seconds left, from the rate of the runs that ended after the first one (None: not known yet)."""
        if self.clock is None:
            return None
        t1, d1 = self.clock
        if done <= d1 or now <= t1:
            return None
        return (now - t1) / (done - d1) * (self.total - done)

    def __call__(self, done: int, failed: int, final: bool = False) -> None:
        now = time.perf_counter()
        if self.clock is None and done > self.done0:
            self.clock = (now, done)
        if not self.enabled:
            return
        if self.tty:
            self._draw(done, failed, final)
            return
        if (not final and now - self.last < 5.0) or (final and self.shown == (done, failed)):
            return
        self.last = now
        self.shown = (done, failed)
        left = self.total - done
        eta = self.eta(done, now) if left else None
        sys.stderr.write(f"{self.label}: {done}/{self.total} runs done, {failed} failed, {left} left, "
                         f"{now - self.t0:.1f} s" + (f", about {eta:.0f} s left" if eta is not None else "") + "\n")
        sys.stderr.flush()

    def _draw(self, done: int, failed: int, final: bool) -> None:
        if self._bar is None and self.clock is not None and not final:
            self._bar = bar(self.label, self.total, initial=self.clock[1], unit="run")  # its rate: after the first run
        if self._bar is not None:
            self._bar.set_postfix_str(f"{failed} failed", refresh=False)
            self._bar.update(done - self._bar.n)
        if final:
            if self._bar is not None:
                self._bar.close()
                self._bar = None
            say(f"{self.label}: {done}/{self.total} runs done, {failed} failed, {self.total - done} left, "
                f"{time.perf_counter() - self.t0:.1f} s")


__all__ = ["Progress", "RunsProgress", "bar", "is_tty", "say"]
