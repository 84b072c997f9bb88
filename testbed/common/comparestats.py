"""Statistics of comparisons between runs (``testbed versus --seeds``, a campaign's summary and ``--table``),
all from ``scipy.stats``.

* a success rate k / n with its **Wilson score interval** (``binomtest(k, n).proportion_ci(method="wilson")``);
* two methods on the same seeds and initial states (paired 0/1 outcomes, the 2x2 table of both, A only,
  B only, neither): the **exact McNemar test** (the two-sided binomial test of the A-only pairs among the
  discordant ones against 1/2: ``binomtest(b, b + c, 0.5)``) and **Newcombe's hybrid score interval** of
  the paired difference p_A - p_B (R. G. Newcombe, Statistics in Medicine 17, 2635-2650, 1998, method 10:
  the Wilson intervals of both rates combined with the phi correlation of the pairs), which keeps its
  coverage at small n and near rates of 0 or 1 where the normal interval collapses to a point;
* paired continuous outcomes (settle time, max norm, saturations): the **Wilcoxon signed-rank test** of the
  differences A - B (zero differences dropped, as Wilcoxon did; exact null distribution without ties, every
  2^m sign assignment with ties up to m = 16 differences, the normal approximation with the tie correction
  above) and a **percentile bootstrap interval of the median difference** (9999 resamples, seeded).

Degenerate cases give values, not exceptions: n = 0 gives None (nothing to estimate), no discordant pair
gives McNemar p = 1, all differences zero give Wilcoxon p = 1 and the interval [0, 0], one pair gives no
interval.  Every function takes plain sequences and returns plain floats (JSON-ready).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, TypeGuard

import numpy as np

#: the confidence level of every interval
CONFIDENCE = 0.95
#: bootstrap resamples of the median difference
RESAMPLES = 9999
#: up to this many nonzero differences with ties, the Wilcoxon p enumerates every sign assignment
EXACT_WITH_TIES = 16

#: the names of the methods, as a summary states them
METHODS = {
    "rate_interval": "95 % Wilson score interval (scipy.stats.binomtest(k, n).proportion_ci(method='wilson'))",
    "paired_rate_test": "exact McNemar test: two-sided binomial test of the discordant pairs against 1/2 "
                        "(scipy.stats.binomtest(b, b + c, 0.5))",
    "paired_rate_interval": "95 % Newcombe hybrid score interval of the paired difference (Newcombe 1998, method 10)",
    "paired_continuous_test": "Wilcoxon signed-rank test of the paired differences, zeros dropped "
                              "(scipy.stats.wilcoxon: exact without ties; every sign assignment with ties up to "
                              f"{EXACT_WITH_TIES} differences; normal approximation with tie correction above)",
    "paired_continuous_interval": f"95 % percentile bootstrap interval of the median difference ({RESAMPLES} "
                                  "resamples, seeded; scipy.stats.bootstrap)",
}


def _stats() -> Any:
    import scipy.stats

    return scipy.stats


def wilson(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float] | None:
    """The Wilson score interval of the proportion ``successes / n`` (None for n = 0)."""
    n, k = int(n), int(successes)
    if n <= 0:
        return None
    ci = _stats().binomtest(k, n).proportion_ci(confidence_level=confidence, method="wilson")
    return max(0.0, float(ci.low)), min(1.0, float(ci.high))


def success_rate(successes: int, n: int) -> dict:
    """``{"n", "successes", "success_rate", "wilson95"}`` (rate and interval None for n = 0)."""
    w = wilson(successes, n)
    return {"n": int(n), "successes": int(successes), "success_rate": successes / n if n else None,
            "wilson95": None if w is None else list(w)}


def mcnemar_exact(b: int, c: int) -> float:
    """The exact (conditional) McNemar p of ``b`` pairs where only A succeeded and ``c`` where only B did:
    the two-sided binomial test of b successes in b + c trials at 1/2; 1.0 when no pair disagrees."""
    b, c = int(b), int(c)
    if b + c == 0:
        return 1.0
    return min(1.0, float(_stats().binomtest(b, b + c, 0.5).pvalue))


def newcombe_paired(both: int, a_only: int, b_only: int, neither: int,
                    confidence: float = CONFIDENCE) -> tuple[float, float] | None:
    """Newcombe's hybrid score interval (1998, method 10) of p_A - p_B from the paired 2x2 table.

    With p_A = (both + a_only) / n, p_B = (both + b_only) / n, their Wilson intervals (l_A, u_A), (l_B, u_B)
    and phi the correlation of the pairs ((both neither - a_only b_only) reduced by n/2 towards 0 when
    positive, over the square root of the product of the four margins; 0 when a margin is empty):

        L = D - sqrt((p_A - l_A)^2 - 2 phi (p_A - l_A)(u_B - p_B) + (u_B - p_B)^2)
        U = D + sqrt((p_B - l_B)^2 - 2 phi (p_B - l_B)(u_A - p_A) + (u_A - p_A)^2)

    None for n = 0."""
    a, b, c, d = int(both), int(a_only), int(b_only), int(neither)
    n = a + b + c + d
    if n == 0:
        return None
    pa, pb = (a + b) / n, (a + c) / n
    wa, wb = wilson(a + b, n, confidence), wilson(a + c, n, confidence)
    assert wa is not None and wb is not None  # n > 0
    (la, ua), (lb, ub) = wa, wb
    margins = (a + b) * (c + d) * (a + c) * (b + d)
    num: float = a * d - b * c
    if margins == 0:
        phi = 0.0
    else:
        num = num - n / 2 if num > n / 2 else (num if num < 0 else 0.0)
        phi = num / math.sqrt(margins)
    diff = pa - pb
    lo = diff - math.sqrt(max(0.0, (pa - la) ** 2 - 2 * phi * (pa - la) * (ub - pb) + (ub - pb) ** 2))
    hi = diff + math.sqrt(max(0.0, (pb - lb) ** 2 - 2 * phi * (pb - lb) * (ua - pa) + (ua - pa) ** 2))
    return max(-1.0, lo), min(1.0, hi)


def paired_binary(a: Sequence[bool | int | None], b: Sequence[bool | int | None]) -> dict:
    """Paired 0/1 outcomes ``a`` and ``b`` (the same seeds, in the same order): the table (``both``,
    ``a_only``, ``b_only``, ``neither``, ``n``), ``difference`` = rate of a - rate of b, its ``ci95``
    (Newcombe) and ``mcnemar_p`` (exact).  n = 0: difference, interval and p None."""
    xa = [bool(x) for x in a]
    xb = [bool(x) for x in b]
    if len(xa) != len(xb):
        raise ValueError(f"paired outcomes of different lengths ({len(xa)} and {len(xb)})")
    both = sum(x and y for x, y in zip(xa, xb))
    a_only = sum(x and not y for x, y in zip(xa, xb))
    b_only = sum(y and not x for x, y in zip(xa, xb))
    n = len(xa)
    ci = newcombe_paired(both, a_only, b_only, n - both - a_only - b_only)
    return {"n": n, "both": both, "a_only": a_only, "b_only": b_only, "neither": n - both - a_only - b_only,
            "difference": (a_only - b_only) / n if n else None, "ci95": None if ci is None else list(ci),
            "mcnemar_p": mcnemar_exact(a_only, b_only) if n else None}


def wilcoxon(d: np.ndarray) -> tuple[float | None, str]:
    """The two-sided Wilcoxon signed-rank p of differences ``d`` (zeros dropped) and how it was computed:
    ``exact`` (no ties), ``all sign assignments`` (ties, at most ``EXACT_WITH_TIES`` nonzero differences),
    ``normal approximation`` (with tie correction); (1.0, ``all differences zero``); (None, ``no pairs``)."""
    d = np.asarray(d, dtype=float)
    if d.size == 0:
        return None, "no pairs"
    nz = d[d != 0]
    if nz.size == 0:
        return 1.0, "all differences zero"
    st = _stats()
    ties = np.unique(np.abs(nz)).size < nz.size
    if not ties and nz.size <= 50:
        how, method = "exact", "exact"
    elif ties and nz.size <= EXACT_WITH_TIES:
        how, method = "all sign assignments", st.PermutationMethod(n_resamples=2 ** nz.size)
    else:
        how, method = "normal approximation", "asymptotic"
    p = float(st.wilcoxon(nz, zero_method="wilcox", method=method).pvalue)
    return min(1.0, p), how


def bootstrap_median(d: np.ndarray, seed: int = 0, n_resamples: int = RESAMPLES) -> tuple[float, float] | None:
    """The 95 % percentile bootstrap interval of the median of ``d`` (resampled with ``seed``); None for
    fewer than 2 values; [v, v] when every value is v."""
    d = np.asarray(d, dtype=float)
    if d.size < 2:
        return None
    if np.all(d == d[0]):
        return float(d[0]), float(d[0])
    res = _stats().bootstrap((d,), np.median, n_resamples=int(n_resamples), method="percentile",
                             confidence_level=CONFIDENCE, rng=np.random.default_rng(seed),
                             batch=max(1, int(2_000_000 // d.size)))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def paired_continuous(a: Sequence[float | None], b: Sequence[float | None], seed: int = 0) -> dict:
    """Paired values ``a`` and ``b`` (None or a non-finite value: that pair is left out, counted in
    ``missing``): ``n`` pairs, ``median_a``, ``median_b``, ``median_difference`` (median of a - b), its
    ``ci95`` (percentile bootstrap), ``wilcoxon_p`` and ``wilcoxon_method``, ``zero_differences``."""
    if len(a) != len(b):
        raise ValueError(f"paired values of different lengths ({len(a)} and {len(b)})")

    def ok(v: float | None) -> TypeGuard[float]:
        return v is not None and not isinstance(v, bool) and math.isfinite(float(v))

    pairs = [(float(x), float(y)) for x, y in zip(a, b) if ok(x) and ok(y)]
    out = {"n": len(pairs), "missing": len(a) - len(pairs)}
    if not pairs:
        return {**out, "median_a": None, "median_b": None, "median_difference": None, "ci95": None,
                "wilcoxon_p": None, "wilcoxon_method": "no pairs", "zero_differences": 0}
    x = np.array([p[0] for p in pairs])
    y = np.array([p[1] for p in pairs])
    d = x - y
    p, how = wilcoxon(d)
    ci = bootstrap_median(d, seed)
    return {**out, "median_a": float(np.median(x)), "median_b": float(np.median(y)),
            "median_difference": float(np.median(d)), "ci95": None if ci is None else list(ci),
            "wilcoxon_p": p, "wilcoxon_method": how, "zero_differences": int(np.sum(d == 0))}
