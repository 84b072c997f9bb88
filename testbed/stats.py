"""Timing statistics of a run's integer-ns stamps (the nodes' summaries and the run summary share them)."""

from __future__ import annotations

import numpy as np

from .wire.messages import NO_TIME


def percentiles(values, unit: float = 1e3) -> dict:
    """p50 / p99 / max / count of ns values, in microseconds by default (None when empty)."""
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
