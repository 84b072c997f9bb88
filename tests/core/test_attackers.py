"""Tests for the attackers package (DoS schedules, budget checker, generators, greedy attacker, gate).

Paper Section II.C: Assumption 3 (N(t) <= kappa_F + rho_F t) and
Assumption 4 (|A(t)| <= kappa_D + rho_D t, rho_D in [0, 1)).
"""

from __future__ import annotations

import ast
import json
import math
import pathlib
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from attackers import (
    GENERATORS,
    GREEDY_STATE_SIZE,
    Gate,
    GreedyAttacker,
    Schedule,
    check,
    greedy_init,
    greedy_params,
    greedy_run,
    greedy_step,
    is_online,
    make_greedy,
    make_schedule,
    realized_rates,
    satisfies,
)

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _scale_tol(kappa, rho, horizon, rel=1e-9):
    """Floating-point allowance for a bound kappa + rho t evaluated up to the horizon."""
    return rel * max(1.0, kappa + rho * horizon)


# --------------------------------------------------------------------------- Schedule
class TestSchedule:
    def test_theta_samples_float_tolerance(self):
        # end of an interval: 14 * 0.1 rounds ABOVE 1.4, still inside [1.0, 1.4]
        assert 14 * 0.1 == 1.4000000000000001 and 1.0 + 0.4 == 1.4
        th = Schedule(((1.0, 0.4),)).theta_samples(0.1, 20)
        assert th.dtype == np.uint8 and th.shape == (20,)
        assert np.flatnonzero(th).tolist() == [10, 11, 12, 13, 14]
        # the brief's example [1.0, 1.5] (15 * 0.1 happens to be exactly 1.5)
        assert np.flatnonzero(Schedule(((1.0, 0.5),)).theta_samples(0.1, 20)).tolist() == list(range(10, 16))
        # start of an interval: 3 * 0.3 rounds BELOW 0.9, still inside [0.9, 1.0]
        assert 3 * 0.3 == 0.8999999999999999
        assert Schedule(((0.9, 0.1),)).theta_samples(0.3, 5).tolist() == [0, 0, 0, 1, 0]

    def test_theta_samples_start_tolerance_and_impulsive(self):
        assert 3 * 0.1 == 0.30000000000000004
        s = Schedule(((0.3, 0.0),))  # impulsive attack at a sampling instant
        assert s.theta_samples(0.1, 6).tolist() == [0, 0, 0, 1, 0, 0]
        # impulsive attack between samples hits nothing
        assert Schedule(((0.25, 0.0),)).theta_samples(0.1, 6).tolist() == [0] * 6

    def test_theta_scalar_and_array(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.0)))
        assert s.theta(1.2) == 1 and isinstance(s.theta(1.2), int)
        assert s.theta(0.99) == 0
        assert s.theta(3.0) == 1 and s.theta(3.0 + 1e-6) == 0
        assert s.theta(1.5000000000000002) == 1  # default relative tolerance
        assert s.theta(1.5000000000000002, eps=0.0) == 0  # exact definition
        out = s.theta(np.array([0.0, 1.0, 1.5, 2.0, 3.0]))
        assert out.dtype == np.uint8 and out.tolist() == [0, 1, 1, 0, 1]
        assert Schedule().theta(np.arange(3.0)).tolist() == [0, 0, 0]

    def test_sorted_and_normalised(self):
        s = Schedule([[3, 1], (1, 0.5), np.array([0.0, 0.0])])
        assert s.intervals == ((0.0, 0.0), (1.0, 0.5), (3.0, 1.0))
        assert all(isinstance(x, float) for p in s.intervals for x in p)
        assert len(s) == 3

    @pytest.mark.parametrize(
        "intervals, word",
        [
            (((-1.0, 1.0),), "a_i"),
            (((1.0, -0.1),), "tau_i"),
            (((math.nan, 1.0),), "finite"),
            (((1.0, math.inf),), "finite"),
            (((1.0, 2.0, 3.0),), "pair"),
            ((("x", 1.0),), "a_i"),
        ],
    )
    def test_validation(self, intervals, word):
        with pytest.raises(ValueError, match=word):
            Schedule(intervals)

    def test_from_theta_runs(self):
        th = [0, 1, 0, 1, 1, 1, 0, 0, 1]
        s = Schedule.from_theta(th, 0.5)
        assert s.intervals == ((0.5, 0.0), (1.5, 1.0), (4.0, 0.0))
        assert Schedule.from_theta([0, 0, 0], 0.1) == Schedule()
        assert Schedule.from_theta([], 0.1) == Schedule()
        with pytest.raises(ValueError):
            Schedule.from_theta([0, 2], 0.1)
        with pytest.raises(ValueError):
            Schedule.from_theta([0, 1], 0.0)

    @FAST
    @given(
        th=st.lists(st.integers(0, 1), max_size=300),
        T=st.floats(1e-3, 10.0, allow_nan=False, allow_infinity=False),
    )
    def test_from_theta_round_trip(self, th, T):
        th = np.array(th, dtype=np.uint8)
        s = Schedule.from_theta(th, T)
        assert np.array_equal(s.theta_samples(T, th.size), th)
        # one attack per maximal run, impulsive iff the run has length 1
        n_runs = int(np.sum(np.diff(np.concatenate(([0], th))) == 1))
        assert len(s) == n_runs
        assert s.total_duration == pytest.approx((th.sum() - n_runs) * T, rel=1e-9, abs=1e-12)

    def test_from_theta_is_one_reading_of_the_losses(self):
        # Impulsive attacks at every sampling instant (rho_F >= 1/T, paper Sec. II.C)
        # cost no duration, but from_theta reads the run of losses as one long attack.
        T = 0.1
        s = Schedule(tuple((k * T, 0.0) for k in range(10)))
        assert satisfies(s, 1.0, 1.0 / T, 0.0, 0.0)
        runs = Schedule.from_theta(s.theta_samples(T, 10), T)
        assert runs.intervals == ((0.0, 9 * T),)
        assert not satisfies(runs, 1.0, 1.0 / T, 0.0, 0.0)

    def test_json_round_trip(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.8)))
        data = json.loads(json.dumps(s.to_list()))
        assert data == [[1.0, 0.5], [3.0, 0.8]]
        assert Schedule.from_list(data) == s

    def test_count_and_union_length(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.8)))
        assert s.count(0.5) == 0 and s.count(1.0) == 1 and s.count(3.0) == 2
        assert s.union_length(1.25) == pytest.approx(0.25)
        assert s.union_length(2.0) == pytest.approx(0.5)
        assert s.union_length(100.0) == pytest.approx(1.3)
        assert s.union_length(-1.0) == 0.0
        np.testing.assert_allclose(s.union_length(np.array([0.0, 1.5, 3.4])), [0.0, 0.5, 0.9])

    @FAST
    @given(
        ivs=st.lists(
            st.tuples(st.floats(0, 20, allow_nan=False), st.floats(0, 5, allow_nan=False)), max_size=12
        ),
        ts=st.lists(st.floats(0, 30, allow_nan=False), min_size=1, max_size=10),
    )
    def test_union_length_matches_naive(self, ivs, ts):
        s = Schedule(tuple(ivs))
        for t in ts:
            # elementary segments between all endpoints; covered iff midpoint is in some interval
            pts = sorted({0.0, t, *[a for a, _ in ivs if a <= t], *[min(a + d, t) for a, d in ivs if a <= t]})
            naive = 0.0
            for p, q in zip(pts[:-1], pts[1:]):
                m = 0.5 * (p + q)
                if any(a <= m <= a + d for a, d in ivs):
                    naive += q - p
            assert s.union_length(t) == pytest.approx(naive, rel=1e-9, abs=1e-9)
            assert s.count(t) == sum(1 for a, _ in ivs if a <= t)


# --------------------------------------------------------------------------- budget checker
class TestBudget:
    def test_hand_computed(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.8)))
        r = check(s, rho_F=0.0, rho_D=0.0)
        assert r.kappa_F_min == 2.0
        assert r.kappa_D_min == pytest.approx(1.3)
        assert r.t_events.tolist() == [0.0, 1.0, 1.5, 3.0, 3.8]
        assert r.N.tolist() == [0, 1, 1, 2, 2]
        np.testing.assert_allclose(r.A, [0.0, 0.0, 0.5, 0.5, 1.3])
        assert r.n_attacks == 2 and r.total_duration == pytest.approx(1.3)

        r = check(s, rho_F=0.5, rho_D=0.2)
        assert r.kappa_F_min == pytest.approx(0.5)  # max(1 - 0.5, 2 - 1.5)
        assert r.kappa_D_min == pytest.approx(1.3 - 0.2 * 3.8)  # at the end of the 2nd attack
        assert r.t_kappa_D == pytest.approx(3.8)

        r = check(s, rho_F=1.0, rho_D=0.5)
        assert r.kappa_F_min == 0.0  # N(t) <= t always
        assert r.kappa_D_min == 0.0  # |A(t)| <= 0.5 t always

    def test_horizon(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.8)))
        r = check(s, 0.0, 0.0, horizon=2.0)
        assert (r.kappa_F_min, r.kappa_D_min, r.n_attacks) == (1.0, 0.5, 1)
        assert r.total_duration == pytest.approx(0.5)
        assert r.t_events[-1] == 2.0
        r = check(s, 0.0, 0.0, horizon=3.4)  # horizon cuts into an attack
        assert r.kappa_D_min == pytest.approx(0.9)
        assert r.n_attacks == 2
        r = check(s, 0.0, 0.0, horizon=0.0)
        assert (r.kappa_F_min, r.kappa_D_min) == (0.0, 0.0)

    def test_overlapping_merged_for_A_counted_for_N(self):
        s = Schedule(((0.0, 2.0), (1.0, 0.5), (1.5, 2.0), (2.5, 0.0)))
        r = check(s, 0.0, 0.0)
        assert r.kappa_F_min == 4.0
        assert r.kappa_D_min == pytest.approx(3.5)
        assert s.merged == ((0.0, 3.5),)
        touching = Schedule(((0.0, 1.0), (1.0, 1.0)))
        r = check(touching, 0.0, 0.0)
        assert (r.kappa_F_min, r.kappa_D_min) == (2.0, 2.0)
        assert touching.count(1.0) == 2

    def test_impulsive_only(self):
        s = Schedule(((0.0, 0.0), (1.0, 0.0), (1.0, 0.0)))
        r = check(s, 1.0, 0.0)
        assert r.kappa_F_min == 2.0  # N(1) = 3 > 1 * 1
        assert r.kappa_D_min == 0.0 and r.total_duration == 0.0

    def test_satisfies(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.8)))
        assert satisfies(s, 2.0, 0.0, 1.3, 0.0)
        assert not satisfies(s, 1.99, 0.0, 1.3, 0.0)
        assert not satisfies(s, 2.0, 0.0, 1.29, 0.0)
        assert satisfies(s, 0.5, 0.5, 0.54, 0.2)
        assert not satisfies(s, 0.49, 0.5, 0.54, 0.2)
        assert satisfies(s, 1.0, 0.0, 0.5, 0.0, horizon=2.0)
        assert satisfies(Schedule(), 0.0, 0.0, 0.0, 0.0)
        assert check(s, 0.0, 0.0).satisfies(2.0, 1.3)

    def test_realized_rates(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.8)))
        r = realized_rates(s, 10.0)
        assert r.rho_F == pytest.approx(0.2) and r.rho_D == pytest.approx(0.13)
        assert realized_rates(s, 2.0) == pytest.approx((0.5, 0.25))
        with pytest.raises(ValueError, match="horizon"):
            realized_rates(s, 0.0)

    @pytest.mark.parametrize(
        "kw, word",
        [
            (dict(rho_F=-1.0, rho_D=0.1), "rho_F"),
            (dict(rho_F=0.1, rho_D=1.0), "rho_D"),
            (dict(rho_F=0.1, rho_D=-0.1), "rho_D"),
            (dict(rho_F=0.1, rho_D=0.1, horizon=-1.0), "horizon"),
        ],
    )
    def test_errors(self, kw, word):
        with pytest.raises(ValueError, match=word):
            check(Schedule(), **kw)


# --------------------------------------------------------------------------- generators
budget_params = st.fixed_dictionaries(
    {
        "kappa_F": st.floats(0.0, 5.0),
        "rho_F": st.floats(0.0, 3.0),
        "kappa_D": st.floats(0.0, 3.0),
        "rho_D": st.floats(0.0, 0.95),
    }
)


class TestGenerators:
    def test_registry(self):
        assert set(GENERATORS) >= {"none", "intervals", "periodic", "random", "greedy"}
        assert is_online("greedy") and not is_online("random") and not is_online("none")
        with pytest.raises(ValueError, match="bogus"):
            is_online("bogus")

    def test_none_and_intervals(self):
        assert make_schedule("none", {}, T=0.1, horizon=10.0) == Schedule()
        assert make_schedule("none", None, T=0.1, horizon=10.0) == Schedule()
        s = make_schedule("intervals", {"intervals": [[3, 0.8], [1, 0.5]]}, T=0.1, horizon=10.0)
        assert s.intervals == ((1.0, 0.5), (3.0, 0.8))
        assert make_schedule("intervals", {"intervals": []}, T=0.1, horizon=1.0) == Schedule()

    def test_periodic_hand(self):
        s = make_schedule("periodic", {"period": 2.0, "length": 0.5, "offset": 1.0}, T=0.1, horizon=7.0)
        assert s.intervals == ((1.0, 0.5), (3.0, 0.5), (5.0, 0.5), (7.0, 0.5))
        s = make_schedule("periodic", {"period": 1.0, "length": 0.0}, T=0.1, horizon=2.5)
        assert s.intervals == ((0.0, 0.0), (1.0, 0.0), (2.0, 0.0))

    @pytest.mark.slow  # half a second or more on a warm cache
    @FAST
    @given(
        period=st.floats(0.1, 10.0),
        frac=st.floats(0.0, 0.99),
        off_frac=st.floats(0.0, 1.0),
    )
    def test_periodic_rates(self, period, frac, off_frac):
        length = frac * period
        horizon = 2000.0 * period
        s = make_schedule(
            "periodic", {"period": period, "length": length, "offset": off_frac * period}, T=0.01, horizon=horizon
        )
        r = realized_rates(s, horizon)
        assert r.rho_F == pytest.approx(1.0 / period, rel=2e-3)
        assert r.rho_D == pytest.approx(length / period, rel=2e-3, abs=1e-12)
        # periodic attacks satisfy Assumptions 3/4 with kappa_F = 1, kappa_D = length
        rep = check(s, 1.0 / period, length / period)
        assert rep.kappa_F_min <= 1.0 + 1e-6
        assert rep.kappa_D_min <= length + 1e-6 * max(1.0, length)

    @FAST
    @given(p=budget_params, seed=st.integers(0, 2**32 - 1), horizon=st.floats(0.0, 200.0))
    def test_random_satisfies_budget(self, p, seed, horizon):
        s = make_schedule("random", p, T=0.1, horizon=horizon, seed=seed)
        rep = check(s, p["rho_F"], p["rho_D"])  # over all t >= 0
        assert rep.kappa_F_min <= p["kappa_F"]
        assert rep.kappa_D_min <= p["kappa_D"] + _scale_tol(p["kappa_D"], p["rho_D"], horizon, 1e-12)
        assert satisfies(s, p["kappa_F"], p["rho_F"], p["kappa_D"], p["rho_D"])
        assert all(a <= horizon and a + tau <= horizon + 1e-9 for a, tau in s.intervals)

    @pytest.mark.parametrize(
        "p",
        [
            dict(kappa_F=1.0, rho_F=0.2, kappa_D=1.0, rho_D=0.3),
            dict(kappa_F=3.0, rho_F=2.0, kappa_D=0.5, rho_D=0.6),
            dict(kappa_F=0.0, rho_F=0.05, kappa_D=0.0, rho_D=0.1),
            dict(kappa_F=2.0, rho_F=1.0, kappa_D=0.2, rho_D=0.9),
        ],
    )
    def test_random_uses_budget(self, p):
        horizon = 3000.0
        for seed in range(3):
            s = make_schedule("random", p, T=0.1, horizon=horizon, seed=seed)
            r = realized_rates(s, horizon)
            assert r.rho_F >= 0.5 * p["rho_F"]
            assert r.rho_D >= 0.5 * p["rho_D"]
            assert any(tau == 0.0 for _, tau in s.intervals)  # some impulsive attacks
            assert len({tau for _, tau in s.intervals}) > 10  # random lengths

    def test_random_deterministic(self):
        p = dict(kappa_F=1.0, rho_F=0.5, kappa_D=1.0, rho_D=0.3)
        a = make_schedule("random", p, T=0.1, horizon=100.0, seed=7)
        b = make_schedule("random", p, T=0.1, horizon=100.0, seed=7)
        c = make_schedule("random", p, T=0.1, horizon=100.0, seed=8)
        d = make_schedule("random", {**p, "seed": 7}, T=0.1, horizon=100.0)
        e = make_schedule("random", p, T=0.1, horizon=100.0, seed=np.random.default_rng(7))
        assert a == b == d == e and a != c
        with pytest.raises(ValueError, match="seed"):
            make_schedule("random", {**p, "seed": 1}, T=0.1, horizon=100.0, seed=2)

    def test_random_zero_budget(self):
        p = dict(kappa_F=0.5, rho_F=0.0, kappa_D=1.0, rho_D=0.5)
        assert make_schedule("random", p, T=0.1, horizon=100.0, seed=0) == Schedule()

    @pytest.mark.parametrize(
        "kind, params, word",
        [
            ("bogus", {}, "bogus"),
            ("periodic", {"period": 1.0}, "length"),
            ("periodic", {"length": 0.1}, "period"),
            ("periodic", {"period": 1.0, "length": 0.1, "phase": 0.0}, "phase"),
            ("periodic", {"period": 1.0, "length": 1.0}, "length"),
            ("periodic", {"period": 0.0, "length": 0.0}, "period"),
            ("periodic", {"period": 1.0, "length": -0.1}, "length"),
            ("periodic", {"period": 1.0, "length": 0.1, "offset": -1.0}, "offset"),
            ("periodic", {"period": "x", "length": 0.1}, "period"),
            ("intervals", {}, "intervals"),
            ("intervals", {"intervals": [[1.0]]}, "intervals"),
            ("intervals", {"intervals": [[-1.0, 1.0]]}, "start"),
            ("intervals", {"intervals": [[1.0, -1.0]]}, "length"),
            ("random", dict(kappa_F=1, rho_F=0.1, kappa_D=1), "rho_D"),
            ("random", dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=1.0), "rho_D"),
            ("random", dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=1.5), "rho_D"),
            ("random", dict(kappa_F=-1, rho_F=0.1, kappa_D=1, rho_D=0.5), "kappa_F"),
            ("random", dict(kappa_F=1, rho_F=-0.1, kappa_D=1, rho_D=0.5), "rho_F"),
            ("random", dict(kappa_F=1, rho_F=0.1, kappa_D=-1, rho_D=0.5), "kappa_D"),
            ("random", dict(kappa_F=1, rho_F=math.nan, kappa_D=1, rho_D=0.5), "rho_F"),
            ("random", dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=0.5, extra=3), "extra"),
            ("greedy", dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=0.5), "online"),
        ],
    )
    def test_errors(self, kind, params, word):
        with pytest.raises(ValueError, match=word):
            make_schedule(kind, params, T=0.1, horizon=10.0, seed=0)

    def test_bad_T_horizon_params(self):
        with pytest.raises(ValueError, match="T"):
            make_schedule("none", {}, T=0.0, horizon=1.0)
        with pytest.raises(ValueError, match="horizon"):
            make_schedule("none", {}, T=0.1, horizon=-1.0)
        with pytest.raises(ValueError, match="dict"):
            make_schedule("none", [1, 2], T=0.1, horizon=1.0)

    def test_make_greedy(self):
        g = make_greedy(dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=0.5, threshold=0.5), T=0.1)
        assert isinstance(g, GreedyAttacker)
        assert g.params.tolist() == [1.0, 0.1, 1.0, 0.5, 0.5] and g.T == 0.1
        for params, word in [
            (dict(kappa_F=1, rho_F=0.1, kappa_D=1), "rho_D"),
            (dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=1.0), "rho_D"),
            (dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=0.5, threshold=2.0), "threshold"),
            (dict(kappa_F=1, rho_F=0.1, kappa_D=1, rho_D=0.5, period=2.0), "period"),
        ]:
            with pytest.raises(ValueError, match=word):
                make_greedy(params, T=0.1)


# --------------------------------------------------------------------------- greedy attacker
class TestGreedy:
    def test_exact_multiple_budget(self):
        # kappa_D = 0.3 = 3 T: one burst over samples 0..3 = interval [0, 0.3], then nothing
        g = GreedyAttacker(1.0, 0.0, 0.3, 0.0, 0.1)
        th = [g.decide(k, 1.0) for k in range(10)]
        assert th == [1, 1, 1, 1, 0, 0, 0, 0, 0, 0]
        assert g.n_attacks == 1

    def test_frequency_and_duration_budget(self):
        # one start per 2 s (rho_F = 0.5), duration 0.2 per second (rho_D = 0.2), kappa_D = 0.3
        g = GreedyAttacker(1.0, 0.5, 0.3, 0.2, 0.1)
        th = np.array([g.decide(k, 1.0) for k in range(2000)], dtype=np.uint8)
        s = Schedule.from_theta(th, 0.1)
        assert satisfies(s, 1.0, 0.5, 0.3, 0.2)
        r = realized_rates(s, 200.0)
        assert r.rho_F == pytest.approx(0.5, abs=0.02)
        assert r.rho_D == pytest.approx(0.2, abs=0.02)

    def test_threshold(self):
        scores = [1.0, 2.0, 0.5, 3.0, 2.9]
        p = dict(kappa_F=10.0, rho_F=0.0, kappa_D=0.0, rho_D=0.0)  # impulsive attacks only
        g1 = GreedyAttacker(**p, T=0.1, threshold=1.0)
        assert [g1.decide(k, s) for k, s in enumerate(scores)] == [1, 0, 0, 1, 0]
        g0 = GreedyAttacker(**p, T=0.1, threshold=0.0)
        assert [g0.decide(k, s) for k, s in enumerate(scores)] == [1, 0, 1, 0, 1]
        g9 = GreedyAttacker(**p, T=0.1, threshold=0.9)
        assert [g9.decide(k, s) for k, s in enumerate(scores)] == [1, 0, 0, 1, 0]
        gn = GreedyAttacker(**p, T=0.1, threshold=0.5)
        assert gn.decide(0, math.nan) == 0

    def test_no_attack_without_budget(self):
        g = GreedyAttacker(0.0, 0.0, 5.0, 0.5, 0.1)
        assert sum(g.decide(k, 1.0) for k in range(100)) == 0
        g = GreedyAttacker(0.0, 1.0, 0.0, 0.0, 0.1)  # first start allowed at t = 1
        th = [g.decide(k, 1.0) for k in range(31)]
        assert np.flatnonzero(th).tolist() == [10, 20, 30]

    def test_k_order(self):
        g = GreedyAttacker(1.0, 0.0, 1.0, 0.0, 0.1)
        assert g.decide(0, 1.0) == 1
        assert g.decide(0, 1.0) == 1  # repeated k: same decision, no state change
        assert g.decide(1, 1.0) == 1
        with pytest.raises(ValueError):
            g.decide(0, 1.0)
        # skipping samples ends the running attack at the last processed sample
        g = GreedyAttacker(2.0, 0.0, 0.2, 0.0, 0.1)
        assert [g.decide(k, 1.0) for k in (0, 1, 5, 6, 7)] == [1, 1, 1, 1, 0]

    def test_state_and_params(self):
        s = greedy_init()
        assert s.shape == (GREEDY_STATE_SIZE,) and s.dtype == np.float64
        p = greedy_params(1, 0.5, 0.3, 0.2, 0.0)
        assert p.dtype == np.float64 and p.tolist() == [1.0, 0.5, 0.3, 0.2, 0.0]
        assert greedy_step(s, 0, 0.1, 1.0, p) == 1
        with pytest.raises(ValueError, match="rho_D"):
            GreedyAttacker(1, 0.5, 0.3, 1.0, 0.1)
        with pytest.raises(ValueError, match="kappa_F"):
            GreedyAttacker(-1, 0.5, 0.3, 0.2, 0.1)
        with pytest.raises(ValueError, match="T"):
            GreedyAttacker(1, 0.5, 0.3, 0.2, 0.0)
        with pytest.raises(ValueError, match="threshold"):
            GreedyAttacker(1, 0.5, 0.3, 0.2, 0.1, threshold=1.5)

    @FAST
    @given(
        p=budget_params,
        T=st.floats(0.001, 2.0),
        threshold=st.floats(0.0, 1.0),
        seed=st.integers(0, 2**32 - 1),
        K=st.integers(0, 3000),
        mode=st.sampled_from(["uniform", "growing", "constant", "spiky"]),
    )
    def test_never_breaks_budget(self, p, T, threshold, seed, K, mode):
        rng = np.random.default_rng(seed)
        if mode == "uniform":
            scores = rng.random(K)
        elif mode == "growing":
            scores = np.exp(0.01 * np.arange(K)) * rng.random(K)
        elif mode == "constant":
            scores = np.ones(K)
        else:
            scores = rng.pareto(1.0, K)
        params = greedy_params(p["kappa_F"], p["rho_F"], p["kappa_D"], p["rho_D"], threshold)
        th = greedy_run(scores, T, params)
        assert th.dtype == np.uint8 and th.shape == (K,)
        s = Schedule.from_theta(th, T)
        assert satisfies(s, p["kappa_F"], p["rho_F"], p["kappa_D"], p["rho_D"])
        rep = check(s, p["rho_F"], p["rho_D"])
        assert rep.kappa_F_min <= p["kappa_F"] + 1e-9
        assert rep.kappa_D_min <= p["kappa_D"] + _scale_tol(p["kappa_D"], p["rho_D"], K * T)
        # the Python wrapper makes the same decisions
        if K <= 400:
            g = GreedyAttacker(p["kappa_F"], p["rho_F"], p["kappa_D"], p["rho_D"], T, threshold=threshold)
            assert [g.decide(k, sc) for k, sc in enumerate(scores)] == th.tolist()


# --------------------------------------------------------------------------- gate
class TestGate:
    def test_schedule_gate(self):
        s = Schedule(((1.0, 0.5), (3.0, 0.0)))
        T = 0.1
        gate = Gate(s, T=T)
        drops = [gate.decide(k, k * T) for k in range(40)]
        assert np.array_equal(np.array(drops, dtype=np.uint8), s.theta_samples(T, 40))
        assert gate.dropped == 7 and gate.forwarded == 33
        assert gate.attacks_started == 2
        assert gate.attack_on is False
        g2 = Gate.from_schedule(s)  # no T: relative tolerance
        assert g2.decide(15, 15 * 0.1) is True and g2.attack_on is True
        gate.reset()
        assert (gate.dropped, gate.forwarded) == (0, 0)

    def test_greedy_gate(self):
        T = 0.1
        scores = np.random.default_rng(1).random(500)
        params = greedy_params(1.0, 0.5, 0.3, 0.2, 0.3)
        expected = greedy_run(scores, T, params)
        gate = Gate(GreedyAttacker(1.0, 0.5, 0.3, 0.2, T, threshold=0.3))
        assert gate.is_online
        drops = [gate.decide(k, k * T, score=sc) for k, sc in enumerate(scores)]
        assert np.array_equal(np.array(drops, dtype=np.uint8), expected)
        assert gate.dropped == int(expected.sum()) and gate.forwarded == 500 - int(expected.sum())

    def test_bad_source(self):
        with pytest.raises(ValueError, match="Schedule"):
            Gate([(1.0, 0.5)])
        with pytest.raises(ValueError, match="T"):
            Gate(GreedyAttacker(1, 0.5, 0.3, 0.2, 0.1), T=0.2)


# --------------------------------------------------------------------------- dependencies
def test_dependencies_only_numpy_numba_stdlib():
    pkg = pathlib.Path(__file__).resolve().parents[2] / "attackers"
    allowed = {"numpy", "numba"} | set(sys.stdlib_module_names)
    for f in pkg.glob("*.py"):
        tree = ast.parse(f.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                mods = [node.module]
            else:
                continue
            for m in mods:
                assert m.split(".")[0] in allowed, f"{f.name} imports {m}"


def test_a_trace_that_declares_a_huge_length_allocates_only_the_run():
    """``n_samples`` comes from a file: it bounds the indices, it never sizes memory."""
    from attackers.generators import gen_trace

    s = gen_trace({"samples": [1, 5, 10**11], "T": 0.1, "n_samples": 10**12}, T=0.1, horizon=3.0, rng=None)
    th = s.theta_samples(0.1, 30)
    assert th.shape == (30,) and np.flatnonzero(th).tolist() == [1, 5]
