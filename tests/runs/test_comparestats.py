"""``testbed.common.comparestats`` (scipy's tests) against the same tests computed here from their definitions, on
known tables: Wilson by its formula, McNemar from the binomial pmf, Newcombe's hybrid score interval by its
formula, the Wilcoxon signed-rank p by enumerating every sign assignment; the degenerate cases."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from testbed.common import comparestats as cs

Z = 1.959963984540054  # the 97.5 % normal quantile


def wilson_by_formula(k: int, n: int) -> tuple[float, float]:
    """Wilson (1927): (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)."""
    p = k / n
    den = 1 + Z * Z / n
    centre = (p + Z * Z / (2 * n)) / den
    half = Z * math.sqrt(p * (1 - p) / n + Z * Z / (4 * n * n)) / den
    return centre - half, centre + half


def mcnemar_by_pmf(b: int, c: int) -> float:
    """Exact McNemar: twice the smaller binomial tail of the discordant pairs at 1/2, at most 1."""
    m = b + c
    if m == 0:
        return 1.0
    tail = sum(math.comb(m, i) for i in range(min(b, c) + 1)) / 2 ** m
    return min(1.0, 2 * tail)


def newcombe_by_formula(a: int, b: int, c: int, d: int) -> tuple[float, float]:
    """Newcombe (1998) method 10, written out: the Wilson limits of both marginal rates and the corrected phi."""
    n = a + b + c + d
    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = wilson_by_formula(a + b, n)
    l2, u2 = wilson_by_formula(a + c, n)
    l1, l2, u1, u2 = max(l1, 0), max(l2, 0), min(u1, 1), min(u2, 1)
    prod = (a + b) * (c + d) * (a + c) * (b + d)
    x = a * d - b * c
    corrected = x - n / 2 if x > n / 2 else (0 if x >= 0 else x)
    phi = 0.0 if prod == 0 else corrected / math.sqrt(prod)
    D = p1 - p2
    dl = math.sqrt((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2)
    du = math.sqrt((p2 - l2) ** 2 - 2 * phi * (p2 - l2) * (u1 - p1) + (u1 - p1) ** 2)
    return D - dl, D + du


def wilcoxon_by_enumeration(d) -> float:
    """Two-sided signed-rank p: zeros dropped, average ranks of |d|, every one of the 2^m sign assignments
    equally likely; P(|W+ - m(m+1)/4| >= observed)."""
    d = [x for x in d if x != 0]
    m = len(d)
    a = sorted(abs(x) for x in d)
    rank = {}
    for v in set(a):
        idx = [i + 1 for i, x in enumerate(a) if x == v]
        rank[v] = sum(idx) / len(idx)
    r = [rank[abs(x)] for x in d]
    w = sum(ri for ri, x in zip(r, d) if x > 0)
    mid = sum(r) / 2
    hits = sum(1 for signs in itertools.product((0, 1), repeat=m)
               if abs(sum(ri for ri, s in zip(r, signs) if s) - mid) >= abs(w - mid) - 1e-9)
    return hits / 2 ** m


@pytest.mark.parametrize("k,n", [(0, 1), (0, 5), (1, 4), (3, 4), (4, 4), (7, 10), (31, 90), (59, 60), (60, 60)])
def test_wilson_equals_its_formula(k, n):
    lo, hi = cs.wilson(k, n)
    flo, fhi = wilson_by_formula(k, n)
    assert lo == pytest.approx(max(flo, 0.0), abs=1e-12) and hi == pytest.approx(min(fhi, 1.0), abs=1e-12)
    assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_wilson_known_value_and_n0():
    lo, hi = cs.wilson(7, 10)  # Newcombe (1998, unpaired paper) Table I: 0.3968 to 0.8922
    assert lo == pytest.approx(0.3968, abs=1e-4) and hi == pytest.approx(0.8922, abs=1e-4)
    assert cs.wilson(0, 0) is None
    assert cs.success_rate(0, 0) == {"n": 0, "successes": 0, "success_rate": None, "wilson95": None}


@pytest.mark.parametrize("b,c", [(0, 0), (0, 1), (1, 0), (0, 4), (2, 7), (5, 5), (6, 16), (1, 12), (20, 3)])
def test_mcnemar_equals_the_binomial_pmf(b, c):
    assert cs.mcnemar_exact(b, c) == pytest.approx(mcnemar_by_pmf(b, c), rel=1e-12, abs=1e-15)


# (both, a only, b only, neither): the examples of Bentur et al. 2009 and Cavo et al. 2012 (Fagerland, Lydersen
# and Laake, Statistical Analysis of Contingency Tables, ch. 8), small tables, and every corner
TABLES = [(1, 1, 7, 12), (59, 6, 16, 80), (10, 0, 0, 20), (4, 0, 0, 0), (0, 0, 0, 4), (2, 2, 0, 0), (0, 3, 1, 0),
          (3, 0, 1, 0), (5, 3, 3, 5), (9, 1, 0, 2), (0, 0, 4, 0), (12, 5, 1, 2)]


@pytest.mark.parametrize("t", TABLES)
def test_newcombe_equals_its_formula(t):
    lo, hi = cs.newcombe_paired(*t)
    flo, fhi = newcombe_by_formula(*t)
    assert lo == pytest.approx(max(flo, -1.0), abs=1e-12) and hi == pytest.approx(min(fhi, 1.0), abs=1e-12)
    n = sum(t)
    assert lo <= (t[1] - t[2]) / n <= hi


def test_paired_binary_no_disagreement_at_small_n_is_not_a_point():
    """The case the normal interval got wrong: n <= 4 and every pair agrees."""
    for n in (1, 2, 3, 4):
        d = cs.paired_binary([True] * n, [True] * n)
        assert d["difference"] == 0.0 and d["mcnemar_p"] == 1.0
        lo, hi = d["ci95"]
        assert lo < 0.0 < hi  # not [0.0, 0.0]
    d = cs.paired_binary([], [])
    assert d["n"] == 0 and d["difference"] is None and d["ci95"] is None and d["mcnemar_p"] is None


def test_paired_binary_counts_the_table():
    a = [1, 1, 0, 0, 1, 0, 1, 1]
    b = [1, 0, 1, 0, 0, 0, 0, 1]
    d = cs.paired_binary(a, b)
    assert (d["both"], d["a_only"], d["b_only"], d["neither"], d["n"]) == (2, 3, 1, 2, 8)
    assert d["difference"] == pytest.approx(2 / 8)
    assert d["mcnemar_p"] == pytest.approx(mcnemar_by_pmf(3, 1))
    assert d["ci95"] == pytest.approx(list(newcombe_by_formula(2, 3, 1, 2)))
    with pytest.raises(ValueError):
        cs.paired_binary([1], [1, 0])


@pytest.mark.parametrize("d", [
    [1.5, -0.5, 2.0, 3.25, -4.0],                      # no ties: scipy's exact distribution
    [0.3, 0.1, -0.2, 0.7, 0.9, 1.1, -0.05, 0.6],
    [1, 2, 3, 4, 5, 6],
    [-1, -2, -3],
    [2, 2, -2, 1, 3, 3, 0, 5],                          # ties and a zero: every sign assignment
    [1, 1, 1, -1, 2, 0, 0],
    [4.0],                                              # one pair
])
def test_wilcoxon_equals_the_enumeration_of_signs(d):
    p, how = cs.wilcoxon(d)
    assert p == pytest.approx(wilcoxon_by_enumeration(d), rel=1e-9)
    ties = len({abs(x) for x in d if x}) < sum(1 for x in d if x)
    assert how == ("all sign assignments" if ties else "exact")


def test_wilcoxon_degenerate_and_large():
    assert cs.wilcoxon([]) == (None, "no pairs")
    assert cs.wilcoxon([0.0, 0.0, 0.0]) == (1.0, "all differences zero")
    rng = np.random.default_rng(5)
    p, how = cs.wilcoxon(np.round(rng.normal(0.4, 1.0, size=80), 1))  # ties, 80 pairs: the normal approximation
    assert how == "normal approximation" and 0.0 < p < 1.0


def test_paired_continuous_bootstrap_seeded_and_degenerate():
    rng = np.random.default_rng(11)
    a = rng.normal(1.0, 1.0, size=25)
    b = a - rng.normal(0.5, 0.3, size=25)
    r1 = cs.paired_continuous(list(a), list(b), seed=3)
    r2 = cs.paired_continuous(list(a), list(b), seed=3)
    assert r1 == r2  # seeded: the same interval again
    lo, hi = r1["ci95"]
    assert lo <= r1["median_difference"] <= hi and r1["median_difference"] == pytest.approx(np.median(a - b))
    assert r1["wilcoxon_p"] == pytest.approx(float(__import__("scipy").stats.wilcoxon(a - b).pvalue))
    # None and non-finite values leave their pair out
    r = cs.paired_continuous([1.0, None, 3.0, float("inf")], [0.0, 2.0, 1.0, 1.0])
    assert r["n"] == 2 and r["missing"] == 2 and r["median_difference"] == pytest.approx(1.5)
    # all differences zero: p 1, interval [0, 0]; one pair: no interval; none: all None
    r = cs.paired_continuous([2, 5, 7], [2, 5, 7])
    assert (r["wilcoxon_p"], r["ci95"], r["median_difference"], r["zero_differences"]) == (1.0, [0.0, 0.0], 0.0, 3)
    r = cs.paired_continuous([3.0], [1.0])
    assert r["n"] == 1 and r["ci95"] is None and r["wilcoxon_p"] == 1.0 and r["median_difference"] == 2.0
    r = cs.paired_continuous([None], [1.0])
    assert r["n"] == 0 and r["median_difference"] is None and r["wilcoxon_p"] is None and r["ci95"] is None
