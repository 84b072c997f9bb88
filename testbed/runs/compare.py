"""``testbed compare A B [--json] [--plot PNG]``: two runs compared sample by sample.

Its arguments and text output are ``testbed.commands.compare``; this module is what it computes.

A and B are each a recording (``.mcap``) or a scenario (bundled name or
``.toml``) to simulate.  A scenario compared with a recording is simulated with
the recording's overrides (``--duration``, ``--T``, ``--mode``, ...), so
``testbed compare live.mcap paper`` asks: did the live run compute exactly what
the simulator computes?

Compared bit for bit (NaN equal to NaN) over the samples both runs have: x, u,
xi and E at the encoder, xi and E at the decoder, theta, the symbols.  Keys of
``--json``: ``identical`` (same number of samples and every value equal),
``first_divergence`` (the first k where any of them differ, or the first
sample only one run has; null when identical), ``max_state_error``
(max_k ||x_A(k) - x_B(k)||_inf over the common samples), ``theta_differs_at``,
``symbols_differ_at`` (the first ``LIST_MAX`` ks; their counts beside), and
per quantity the first k where it differs (``differs_first``).

Exit codes: 0 compared (identical or not), 2 unusable input.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..scenario import Scenario
    from .run import Run

LIST_MAX = 1000
QUANTITIES = ("x", "u", "xi", "E", "xi_dec", "E_dec", "theta", "symbols")


def _is_recording(ref: str) -> bool:
    p = Path(ref)
    if p.suffix.lower() == ".mcap":
        return True
    if p.suffix.lower() == ".toml" or not p.is_file():
        return False
    with open(p, "rb") as f:
        return f.read(8) == b"\x89MCAP0\r\n"


def load_side(ref: str | Path | Scenario | Run, other_overrides: dict | None = None, *,
              trust_code: bool = False) -> Run:
    """A ``testbed.runs.run.Run`` from a recording path (``trust_code`` as in ``testbed.runs.run.open``), a
    scenario, or a ``Run`` as it is."""
    from .run import Run, simulate
    from .run import open as open_run

    if isinstance(ref, Run):
        return ref
    if _is_recording(str(ref)):
        assert isinstance(ref, (str, Path))  # a recording is a path
        return open_run(ref, trust_code=trust_code)
    return simulate(ref, **(other_overrides or {}))


def _overrides(run: Run | None) -> dict:
    if run is None or not run.metadata:
        return {}
    try:
        over = json.loads(run.metadata.get("testbed.run", {}).get("scenario_overrides", "{}") or "{}")
    except ValueError:
        return {}
    return over if isinstance(over, dict) else {}


def _differs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row: some value differs (bit for bit; NaN equals NaN)."""
    a = np.asarray(a)
    b = np.asarray(b)
    if a.dtype.kind == "f" or b.dtype.kind == "f":
        a, b = a.astype(float), b.astype(float)
        d = ~((a == b) | (np.isnan(a) & np.isnan(b)))
    else:
        d = a != b
    return d.reshape(len(d), -1).any(axis=1) if d.ndim > 1 else d


def load_pair(a: str | Path | Scenario | Run, b: str | Path | Scenario | Run, *,
              trust_code: bool = False) -> tuple[Run, Run]:
    """Both sides as ``Run``s; a scenario opposite a recording gets the recording's overrides."""
    if _is_scenario_ref(a) and not _is_scenario_ref(b):
        rb = load_side(b, trust_code=trust_code)
        return load_side(a, _overrides(rb)), rb
    ra = load_side(a, trust_code=trust_code)
    return ra, load_side(b, _overrides(ra), trust_code=trust_code)


def compare(a: str | Path | Scenario | Run, b: str | Path | Scenario | Run, *, trust_code: bool = False) -> dict:
    """The comparison of two runs (recordings, scenarios or ``Run`` objects) as a JSON-able dict."""
    ra, rb = load_pair(a, b, trust_code=trust_code)
    A, B = ra.arrays, rb.arrays
    n = min(ra.N, rb.N)
    first = {}
    per = {}
    for q in QUANTITIES:
        if q not in A or q not in B or np.shape(A[q])[1:] != np.shape(B[q])[1:]:
            first[q] = 0 if n else None
            per[q] = np.ones(n, dtype=bool)
            continue
        d = _differs(A[q][:n], B[q][:n])
        per[q] = d
        idx = np.flatnonzero(d)
        first[q] = int(idx[0]) if idx.size else None
    cands = [v for v in first.values() if v is not None]
    if ra.N != rb.N:
        cands.append(n)
    fd = min(cands) if cands else None
    xa, xb = np.asarray(A["x"][:n], dtype=float), np.asarray(B["x"][:n], dtype=float)
    if xa.shape == xb.shape and n:
        err = np.abs(xa - xb).reshape(n, -1).max(axis=1)
        both = np.isfinite(err)
        max_err = float(err[both].max()) if both.any() else None
    else:
        max_err = None
    th, sy = np.flatnonzero(per["theta"]), np.flatnonzero(per["symbols"])
    return {
        "a": _describe(a, ra), "b": _describe(b, rb),
        "samples": {"a": ra.N, "b": rb.N, "compared": n},
        "identical": fd is None,
        "first_divergence": fd,
        "max_state_error": max_err,
        "theta_differs_at": th[:LIST_MAX].tolist(), "theta_differs": int(th.size),
        "symbols_differ_at": sy[:LIST_MAX].tolist(), "symbols_differ": int(sy.size),
        "differs_first": first,
    }


def _is_scenario_ref(ref: object) -> bool:
    from .run import Run

    return not isinstance(ref, Run) and not _is_recording(str(ref))


def _describe(ref: object, run: Run) -> dict:
    return {"ref": str(ref) if not hasattr(ref, "arrays") else repr(ref), "source": run.source,
            "scenario": run.scenario.name, "T": run.scenario.T, "samples": run.N}


def plot(a_run: Run, b_run: Run, path: str | Path, *, title: str = "", size: str = "page") -> Path:
    """States of both runs over t (A solid, B dashed), ||x_A - x_B||_inf, the lost samples of each, DoS shaded."""
    from ..analysis.figures import plot_compare

    return plot_compare(a_run, b_run, path, title=title, size=size)


__all__ = ["compare", "load_side", "load_pair", "plot", "QUANTITIES"]
