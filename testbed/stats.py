"""Timing statistics of a run's integer-ns stamps (the nodes' summaries and the run summary share them)."""

from __future__ import annotations

import numpy as np

from .wire.messages import NO_TIME


class Timings:
    """ns values a node collects for its percentiles, in a fixed amount of memory however long the run.

    Every value is kept up to ``cap`` of them (the percentiles are then exact); beyond that a uniform
    random sample of ``cap`` values (reservoir sampling, Algorithm R, with a fixed seed) stands for
    them, while the count and the maximum stay exact.  With the default cap of 65,536 values (512 KiB)
    p50 and p99 are off by less than about 0.1 percentile points (the sample's standard error); a run
    of up to 65,536 samples (11 minutes at T = 10 ms) is exact.
    """

    CAP = 65536

    def __init__(self, cap: int = CAP, seed: int = 0):
        self._a = np.empty(int(cap), dtype=np.int64)
        self.n = 0
        self.max: int | None = None
        self._rng = np.random.default_rng(seed)

    def append(self, v: int) -> None:
        if v == NO_TIME:
            return
        cap = len(self._a)
        if self.n < cap:
            self._a[self.n] = v
        else:
            j = int(self._rng.integers(0, self.n + 1))
            if j < cap:
                self._a[j] = v
        self.n += 1
        if self.max is None or v > self.max:
            self.max = v

    def __len__(self) -> int:
        return self.n

    def values(self) -> np.ndarray:
        """The values kept (all of them, or the sample)."""
        return self._a[:min(self.n, len(self._a))]


def percentiles(values, unit: float = 1e3) -> dict:
    """p50 / p99 / max / count of ns values, in microseconds by default (None when empty)."""
    if isinstance(values, Timings):
        if values.n == 0:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        a = values.values().astype(float)
        return {"p50": float(np.percentile(a, 50) / unit), "p99": float(np.percentile(a, 99) / unit),
                "max": float(values.max / unit), "n": int(values.n)}
    if isinstance(values, np.ndarray) and values.dtype.kind in "iu":
        a = values[values != NO_TIME].astype(float)
    else:
        a = np.asarray([v for v in values if v is not None and v != NO_TIME], dtype=float)
    if a.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": float(np.percentile(a, 50) / unit), "p99": float(np.percentile(a, 99) / unit),
            "max": float(a.max() / unit), "n": int(a.size)}


def fmt_percentiles(p: dict | None) -> str:
    """Percentiles in microseconds as one line of text (``testbed run``, ``testbed report``)."""
    if not p or p.get("p50") is None:
        return "n/a"
    return f"p50 {p['p50']:.0f} us, p99 {p['p99']:.0f} us, max {p['max']:.0f} us"
