"""Unit tests of the analysis numerics (Theorem 1, Theorem 2, the LMI solver, remainder bounds).

Pure numerics, no simulation: cases with a known answer (scalar and linear plants,
where g = 0), independent recomputation of the formulas, and the monotonic facts.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

import plants
from testbed.analysis import lmi
from testbed.analysis.region import allowable_region
from testbed.analysis.theorem1 import (
    Loop,
    common_P,
    lyapunov_margin,
    make_certificate,
    min_condition_P,
    min_relative_condition,
    mu_pair,
    plain_certificate,
    stability_lhs,
)
from testbed.analysis.theorem2 import (
    RemainderRadius,
    _PData,
    evaluate,
    gamma_for_delta,
    inf_norm,
    lemma_constants,
    theorem2,
    theorem2_auto,
)
from testbed.loop.control import c2d


# ----------------------------------------------------------------------------- fixtures
def paper_loop() -> Loop:
    """The paper's Lienard loop (Section V): T = 0.1, M = 6, L = 10, K = [-1.81 -1.90]."""
    p = plants.make("lienard")
    A, B = p.linearization()
    return Loop(A=A, B=B, K=np.array([[-1.81, -1.90]]), T=0.1, M=6, Lambda=math.exp(1.0))


def scalar_loop(a=0.5, b=1.0, k=-2.0, T=0.1, M=6, L=1.0) -> Loop:
    return Loop(A=np.array([[a]]), B=np.array([[b]]), K=np.array([[k]]), T=T, M=M, Lambda=math.exp(L * T))


@pytest.fixture(scope="module")
def lienard():
    return paper_loop()


@pytest.fixture(scope="module")
def lienard_regions(lienard):
    return {rule: allowable_region(lienard, rule, n_phi0=24, n_phi1=4) for rule in ("paper", "tight")}


# ----------------------------------------------------------------------------- the loop
def test_loop_matches_paper_numbers(lienard):
    assert lienard.rho0 == pytest.approx(0.951, abs=1e-3)
    assert lienard.rho1 == pytest.approx(math.exp(0.05), rel=1e-12)   # eig(A) = 0.5 +- 0.866 i
    assert lienard.Lambda == pytest.approx(2.718281828, rel=1e-9)
    lo, hi = lienard.phi0_range
    assert lo == pytest.approx(lienard.rho0 ** 2) and hi == 1.0
    assert lienard.phi1_min == pytest.approx(math.e ** 2)            # Lambda^2 > rho(A~)^2


# ----------------------------------------------------------------------------- (stability)
def test_stability_lhs_by_hand():
    T, mu0, mu1, nu0, nu1 = 0.1, 1.7, 2.3, 0.9, 7.0
    rF, rD = 0.3, 0.02
    rs = rD + rF * T
    expect = rF * T * math.log(mu0 * mu1) + (1 - rs) * math.log(nu0) + rs * math.log(nu1)
    assert stability_lhs(rF, rD, T, mu0, mu1, nu0, nu1) == pytest.approx(expect, rel=1e-14)
    # no attack: the condition is ln nu0 < 0
    assert stability_lhs(0.0, 0.0, T, mu0, mu1, nu0, nu1) == pytest.approx(math.log(nu0))


def test_scalar_plant_region_by_hand():
    """n = 1: every P > 0 is optimal (cond 1), so mu0 mu1 = 1 and the region is
    rho_D + rho_F T < ln(1/nu0) / ln(nu1/nu0) with nu0 -> max(Phi0^2, Lambda^2/M^2), nu1 = Lambda^2."""
    loop = scalar_loop()
    a, b, k, T = 0.5, 1.0, -2.0, 0.1
    Ad = math.exp(a * T)
    Bd = (math.exp(a * T) - 1) / a * b
    Phi0 = Ad + Bd * k
    assert_allclose(loop.Phi0, [[Phi0]], rtol=1e-12)
    nu0 = max(Phi0 ** 2, loop.Lambda ** 2 / loop.M ** 2)
    nu1 = max(loop.Lambda ** 2, Ad ** 2 * (1 + 1e-6))
    sup = math.log(1 / nu0) / math.log(nu1 / nu0)           # supremum over phi_0 -> nu0
    for rule in ("paper", "tight"):
        reg = allowable_region(loop, rule, n_phi0=12, n_phi1=3)
        assert np.allclose(reg.a, 0.0, atol=1e-9)
        # attained at the smallest phi_0 of the grid, within 1e-3 of the supremum
        nu0_grid = max(reg.phi0.min(), loop.Lambda ** 2 / loop.M ** 2)
        rho_D_max = math.log(1 / nu0_grid) / math.log(nu1 / nu0_grid)
        assert reg.rho_D_max == pytest.approx(rho_D_max, rel=1e-12)
        assert sup * (1 - 1e-3) < reg.rho_D_max <= sup
        assert reg.rho_F_max == pytest.approx(rho_D_max / T, rel=1e-12)
        # boundary is the line rho_D + rho_F T = rho_D_max
        assert_allclose(reg.rho_F, (reg.rho_D_max - reg.rho_D) / T, rtol=1e-9, atol=1e-9)


def test_certificates_satisfy_strict_lyapunov_inequalities(lienard, lienard_regions):
    for rule, reg in lienard_regions.items():
        for i in range(len(reg.phi0)):
            for j in range(len(reg.phi1)):
                c = reg.certificate(i, j)
                v = c.verify(lienard.Phi0, lienard.Phi1)
                assert v["ok"], (rule, i, j, v)
                # by eigenvalues, independently of verify()
                S0 = lienard.Phi0.T @ c.P0 @ lienard.Phi0 - c.phi0 * c.P0
                S1 = lienard.Phi1.T @ c.P1 @ lienard.Phi1 - c.phi1 * c.P1
                assert np.linalg.eigvalsh(S0).max() < 0 and np.linalg.eigvalsh(S1).max() < 0
                assert np.linalg.eigvalsh(c.P0).min() > 0 and np.linalg.eigvalsh(c.P1).min() > 0
                assert c.rho_D_max <= reg.rho_D_max + 1e-12 and c.rho_F_max <= reg.rho_F_max + 1e-12


def test_mu_constants_follow_mu0_mu1(lienard, lienard_regions):
    c = lienard_regions["paper"].best_area()
    P0, P1 = c.P0, c.P1
    l0, l1 = np.linalg.eigvalsh(P0), np.linalg.eigvalsh(P1)
    mu0 = max(l1[-1] / l0[0], c.eta1 / c.eta0)
    mu1 = max(l0[-1] / l1[0], c.eta0 / c.eta1)
    assert c.mu == pytest.approx((mu0, mu1), rel=1e-12)
    # eta chosen so as not to dominate: mu0 mu1 = cond(P0) cond(P1)
    assert mu0 * mu1 == pytest.approx(l0[-1] / l0[0] * l1[-1] / l1[0], rel=1e-9)
    # the (mu) property itself: W1 <= mu0 W0 and W0 <= mu1 W1 on random (xi, E)
    rng = np.random.default_rng(0)
    for _ in range(200):
        xi, E = rng.normal(size=2), abs(rng.normal())
        W0 = xi @ P0 @ xi + c.eta0 * E * E
        W1 = xi @ P1 @ xi + c.eta1 * E * E
        assert W1 <= mu0 * W0 * (1 + 1e-12) and W0 <= mu1 * W1 * (1 + 1e-12)
    # the tight constants are never larger
    t0, t1 = mu_pair(P0, P1, c.eta0, c.eta1, "tight")
    assert t0 * t1 <= mu0 * mu1 * (1 + 1e-12)


def test_optimized_beats_plain_choice(lienard, lienard_regions):
    plain = plain_certificate(lienard)
    assert plain.verify(lienard.Phi0, lienard.Phi1)["ok"]
    reg = lienard_regions["paper"]
    assert reg.rho_D_max > plain.rho_D_max and reg.rho_F_max > plain.rho_F_max
    rd = np.linspace(0, plain.rho_D_max * 0.999, 30)
    assert np.all(reg.envelope(rd)[0] >= plain.boundary(rd) - 1e-12)
    assert lienard_regions["tight"].rho_F_max >= reg.rho_F_max


def test_lienard_intercepts(lienard, lienard_regions):
    """rho_D_max = ln(1/nu0) / ln(nu1/nu0) with nu0 -> rho(Phi0)^2, nu1 = Lambda^2 = e^2 (independent of P)."""
    sup = math.log(1 / lienard.rho0 ** 2) / math.log(math.e ** 2 / lienard.rho0 ** 2)
    assert sup == pytest.approx(0.04744, abs=1e-5)
    for reg in lienard_regions.values():
        assert sup * (1 - 1e-3) < reg.rho_D_max <= sup
    # tight rule: a common P exists for every phi, mu0 mu1 = 1 and rho_F_max = rho_D_max / T
    tight = lienard_regions["tight"]
    assert np.all(tight.a == 0.0)
    assert tight.rho_F_max == pytest.approx(tight.rho_D_max / lienard.T, rel=1e-12)


def test_larger_rho_D_never_enlarges_allowable_rho_F(lienard_regions):
    for reg in lienard_regions.values():
        rd = np.linspace(0, reg.rho_D_max * 1.2, 400)
        rf, _ = reg.envelope(rd)
        assert np.all(np.diff(rf) <= 1e-15)
        assert rf[-1] == 0.0


@settings(max_examples=60, deadline=None)
@given(rF=st.floats(0, 0.6), rD=st.floats(0, 0.06), u=st.floats(0, 1), v=st.floats(0, 1))
def test_allowable_region_is_a_down_set(lienard_regions, rF, rD, u, v):
    """If (rho_F, rho_D) is allowed, so is every weaker attack (u rho_F, v rho_D)."""
    for reg in lienard_regions.values():
        if reg.holds(rF, rD):
            assert reg.holds(u * rF, v * rD)
            assert rF <= reg.envelope([rD])[0][0] + 1e-12


# ----------------------------------------------------------------------------- LMI solver
def test_lmi_solver_known_answer():
    # minimize t s.t. [[t, 1], [1, t]] > 0  ->  t* = 1
    blk = lmi.Block(np.array([[0.0, 1.0], [1.0, 0.0]]), np.array([np.eye(2)]))
    res = lmi.barrier_minimize(np.array([1.0]), [blk], np.array([3.0]))
    assert res.value == pytest.approx(1.0, abs=1e-6) and res.value > 1.0
    # phase I: max t with diag(1 - x, 1 + x) - t I >= 0 -> x = 0, t = 1
    blk2 = lmi.Block(np.eye(2), np.array([np.diag([-1.0, 1.0])]))
    x, t = lmi.max_margin([blk2], np.array([0.7]), stop_at=None)
    assert t == pytest.approx(1.0, abs=1e-5) and x[0] == pytest.approx(0.0, abs=1e-3)
    with pytest.raises(ValueError):
        lmi.barrier_minimize(np.array([1.0]), [blk], np.array([0.5]))


def test_min_condition_P_normal_matrix_is_identity():
    """For a normal Phi (scaled rotation) P = I is optimal: cond 1."""
    th = 0.3
    Phi = 0.9 * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    P, k = min_condition_P(Phi, 0.82)
    assert k == pytest.approx(1.0, abs=1e-4)
    assert lyapunov_margin(Phi, P, 0.82) < 0


@pytest.mark.slow  # half a second or more on a warm cache
def test_min_condition_P_against_brute_force():
    """A non-normal Phi: the LMI optimum is no worse than a brute-force search over P = [[1, p], [p, q]]."""
    Phi = np.array([[0.8, 0.5], [0.0, 0.7]])
    phi = 0.75
    P, k = min_condition_P(Phi, phi)
    assert lyapunov_margin(Phi, P, phi) < 0
    best = math.inf
    for p in np.linspace(-3, 3, 241):
        for q in np.geomspace(0.05, 50, 241):
            Q = np.array([[1.0, p], [p, q]])
            ev = np.linalg.eigvalsh(Q)
            if ev[0] <= 0:
                continue
            if np.linalg.eigvalsh(Phi.T @ Q @ Phi - phi * Q).max() < 0:
                best = min(best, ev[-1] / ev[0])
    assert math.isfinite(best)
    assert k <= best * (1 + 1e-3)
    assert k >= best * 0.9   # and the grid is fine enough to come close


def test_tight_rule_without_common_P():
    """A case where no common P exists: the bisection returns an admissible pair with product in (1, paper]."""
    Phi0 = np.array([[0.5, 3.0], [0.0, 0.5]])
    Phi1 = np.array([[1.05, 0.0], [3.0, 1.05]])
    phi0, phi1 = 0.5, 1.3
    assert common_P(Phi0, phi0, Phi1, phi1) is None
    P0, k0 = min_condition_P(Phi0, phi0)
    P1, k1 = min_condition_P(Phi1, phi1)
    Q0, Q1, mu = min_relative_condition(Phi0, phi0, Phi1, phi1, P0_start=P0, P1_start=P1)
    assert lyapunov_margin(Phi0, Q0, phi0) < 0 and lyapunov_margin(Phi1, Q1, phi1) < 0
    ev = np.linalg.eigvals(np.linalg.solve(Q0, Q1)).real
    assert mu == pytest.approx(ev.max() / ev.min(), rel=1e-6)
    assert 1.0 < mu <= k0 * k1 * (1 + 1e-9)


def test_make_certificate_balances_mu():
    loop = paper_loop()
    P0, _ = min_condition_P(loop.Phi0, 0.93)
    P1, _ = min_condition_P(loop.Phi1, loop.phi1_min)
    for rule in ("paper", "tight"):
        c = make_certificate(loop, 0.93, loop.phi1_min, P0, 3.7 * P1, rule=rule)
        assert np.linalg.eigvalsh(c.P0)[0] == pytest.approx(1.0)
        assert c.mu0 == pytest.approx(c.mu1, rel=1e-9)


# ----------------------------------------------------------------------------- remainder bounds
@pytest.mark.slow  # half a second or more on a warm cache
@pytest.mark.parametrize("name", plants.names())
def test_remainder_gain_contract(name):
    p = plants.make(name)
    rs = [0.01, 0.05, 0.2]
    G = [p.remainder_gain(r) for r in rs]
    assert all(g >= 0 and math.isfinite(g) for g in G)
    assert G == sorted(G)                       # nondecreasing in r
    # it bounds the remainder on random points of the box
    rng = np.random.default_rng(1)
    r = 0.2
    X = rng.uniform(-r, r, (2000, p.n))
    U = rng.uniform(-r, r, (2000, p.m))
    lhs = np.max(np.abs(p.remainder(X, U)), axis=1)
    rhs = G[-1] * (np.max(np.abs(X), axis=1) + np.max(np.abs(U), axis=1))
    assert np.all(lhs <= rhs * (1 + 1e-9) + 1e-15)


@pytest.mark.slow  # half a second or more on a warm cache
@pytest.mark.parametrize("name", ["lienard", "pendulum"])
def test_exact_remainder_gain_matches_numerical_estimate(name):
    p = plants.make(name)
    for r in (0.1, 0.7, 2.0):
        exact = p.remainder_gain(r)
        numeric = plants.Plant.remainder_gain(p, r)
        assert numeric == pytest.approx(exact, rel=1e-6)


def test_lienard_remainder_gain_formula():
    p = plants.make("lienard", a=1 / 3, b=1 / 50)
    assert p.remainder_gain(0.5) == pytest.approx(1 / 3 * 0.25 - 0.02 * 0.0625)
    # beyond the vertex s = a / (2 b) = 8.33 the maximum of |a s - b s^2| is max(vertex, end)
    assert p.remainder_gain(3.0) == pytest.approx(max((1 / 3) ** 2 / (4 * 0.02), abs(3 - 0.02 * 81)))
    assert plants.make("linear").remainder_gain(10.0) == 0.0


def test_remainder_radius_inverts_the_gain():
    p = plants.make("lienard")
    rad = RemainderRadius(p)
    for gamma in (1e-12, 1e-4, 0.05, 1.0):
        r = rad(gamma)
        assert p.remainder_gain(r) <= gamma < p.remainder_gain(r * (1 + 1e-7))
    # d' of the paper's Lienard plant: a r^2 - b r^4 = 1
    a, b = 1 / 3, 1 / 50
    assert rad(1.0) == pytest.approx(math.sqrt((a - math.sqrt(a * a - 4 * b)) / (2 * b)), rel=1e-8)
    assert RemainderRadius(plants.make("linear"))(1e-3) == math.inf


# ----------------------------------------------------------------------------- Theorem 2
def test_lemma_constants_by_hand(lienard):
    p = plants.make("lienard")
    gamma = 1e-3
    lem = lemma_constants(lienard, RemainderRadius(p), gamma, varrho=4.0)
    T = 0.1
    nA, nK, nBK = 2.0, 3.71, 3.71          # ||A|| = 2, ||K|| = ||B K|| = 1.81 + 1.90
    c0 = (1 + T * (nBK + nK)) * math.exp(T * (nA + 1))
    c1 = math.exp(T * (nA + 1))
    assert lem.c0 == pytest.approx(c0, rel=1e-12) and lem.c0 == pytest.approx(2.35145, rel=1e-5)
    assert lem.c1 == pytest.approx(c1, rel=1e-12)
    assert lem.gamma0 == pytest.approx((c0 + nK) * gamma * T * math.exp(T * nA), rel=1e-12)
    assert lem.gamma1 == pytest.approx(c1 * gamma * T * math.exp(T * nA), rel=1e-12)
    scale = math.sqrt(c0 ** 2 + nK ** 2)
    assert lem.d == pytest.approx(lem.d_prime / scale)
    # delta' solves a r^2 - b r^4 = gamma
    s = (1 / 3 - math.sqrt(1 / 9 - 4 * 0.02 * gamma)) / (2 * 0.02)
    assert lem.delta_prime == pytest.approx(math.sqrt(s), rel=1e-8)
    assert lem.delta == pytest.approx(min(lem.d, lem.delta_prime / scale), rel=1e-12)


def test_paper_delta_order_of_magnitude(lienard):
    """delta = 1.94e-7 (Section V) is reached with gamma ~ 2.4e-13 under the exact Lienard bound."""
    p = plants.make("lienard")
    g = gamma_for_delta(lienard, p, 1.94e-7)
    assert 1e-13 < g < 1e-12
    lem = lemma_constants(lienard, RemainderRadius(p), g, varrho=4.0)
    assert lem.delta == pytest.approx(1.94e-7, rel=1e-6)


@pytest.mark.slow  # half a second or more on a warm cache
def test_linear_plant_nonlinear_constants_vanish():
    """g = 0: with gamma = 0, gamma0 = gamma1 = 0, phi^_p = phi_p and delta (and the E0 bound) unbounded."""
    lin = plants.make("linear", A=[[0.0, 1.0], [2.0, -1.0]], B=[[0.0], [1.0]])
    A, B = lin.linearization()
    T = 0.1
    Ad, Bd = c2d(A, B, T)
    from testbed.loop.control import dlqr

    K = dlqr(Ad, Bd, np.eye(2), np.eye(1))
    loop = Loop(A=A, B=B, K=K, T=T, M=8, Lambda=math.exp(3.0 * T))
    reg = allowable_region(loop, "paper", n_phi0=8, n_phi1=2)
    cert = reg.best_area()
    r = theorem2(loop, lin, cert, 0.0, (1.0, 0.0, 0.2, 0.0))
    assert r.lemma.gamma0 == 0 and r.lemma.gamma1 == 0
    assert math.isinf(r.lemma.delta) and math.isinf(r.lemma.d)
    assert r.phi0_hat == pytest.approx(cert.phi0) and r.phi1_hat == pytest.approx(cert.phi1)
    assert r.holds and math.isinf(r.E0_bound)
    assert r.E0_factor > 0
    auto = theorem2_auto(loop, lin, cert, (1.0, 0.0, 0.2, 0.0))
    assert math.isinf(auto.E0_bound)


def test_theorem2_constants_recomputed(lienard, lienard_regions):
    p = plants.make("lienard")
    budget = (1.0, 0.05, 0.5, 0.01)
    cert = lienard_regions["paper"].best_for(budget[1], budget[3])
    r = theorem2(lienard, p, cert, 1e-4, budget)
    assert r.holds
    n, M, Lam, T = 2, 6, math.e, 0.1
    P0, P1 = cert.P0, r.s * cert.P1
    lmin0 = np.linalg.eigvalsh(P0)[0]
    phi0_hat = cert.phi0 + n * (2 * r.lemma.gamma0 * inf_norm(P0 @ lienard.Phi0)
                                + r.lemma.gamma0 ** 2 * inf_norm(P0)) / lmin0
    assert r.phi0_hat == pytest.approx(phi0_hat, rel=1e-12)
    phi0_tilde = phi0_hat + n * inf_norm(P0) / (r.eps * lmin0)
    vartheta = (1 + r.eps) * n * inf_norm(P0)
    omega0 = max(phi0_tilde, vartheta / r.eta0 * ((M - 1) / M) ** 2 + Lam ** 2 / M ** 2)
    assert r.omega0 == pytest.approx(omega0, rel=1e-12)
    lmin1 = np.linalg.eigvalsh(P1)[0]
    phi1_hat = cert.phi1 + n * (2 * r.lemma.gamma1 * inf_norm(P1 @ lienard.Phi1)
                                + r.lemma.gamma1 ** 2 * inf_norm(P1)) / lmin1
    assert r.omega1 == pytest.approx(max(phi1_hat, Lam ** 2), rel=1e-9)
    l0, l1 = np.linalg.eigvalsh(P0), np.linalg.eigvalsh(P1)
    mu0 = max(l1[-1] / l0[0], r.eta1 / r.eta0)
    mu1 = max(l0[-1] / l1[0], r.eta0 / r.eta1)
    assert (r.mu0, r.mu1) == pytest.approx((mu0, mu1), rel=1e-9)
    alpha = 0.5 * min(l0[0], r.eta0, l1[0], r.eta1)
    beta = max(n * l0[-1], r.eta0, n * l1[-1], r.eta1)
    assert (r.alpha, r.beta) == pytest.approx((alpha, beta), rel=1e-9)
    kF, rF, kD, rD = budget
    rs = rD + rF * T
    omega = (mu0 * mu1) ** (rF * T) * r.omega0 ** (1 - rs) * r.omega1 ** rs
    assert r.omega == pytest.approx(omega, rel=1e-9) and omega < 1
    kDs = kD + kF * T
    E0 = (mu0 * mu1) ** (-kF / 2) * (r.omega0 / r.omega1) ** (kDs / (2 * T)) * r.delta * math.sqrt(alpha / beta)
    assert r.E0_bound == pytest.approx(E0, rel=1e-9)
    # the (alpha_beta) sandwich on random (xi, E)
    rng = np.random.default_rng(2)
    for _ in range(200):
        xi, E = rng.normal(size=2), abs(rng.normal())
        s2 = (np.max(np.abs(xi)) + E) ** 2
        for P, eta in ((P0, r.eta0), (P1, r.eta1)):
            W = xi @ P @ xi + eta * E * E
            assert alpha * s2 <= W * (1 + 1e-12) and W <= beta * s2 * (1 + 1e-12)


def test_theorem2_choice_does_not_move_with_the_last_bits_of_the_certificate(lienard, lienard_regions):
    """The search for (s, epsilon, eta_0, eta_1) stops at the same choice for a certificate whose P_0 and P_1
    differ in their last bits (as one machine's BLAS from another's), so the bound and its constants are the
    same to 9 digits (what ``docs/make_figures.py --check`` compares); the bound holds on the exact inputs."""
    import dataclasses

    p = plants.make("lienard")
    cert = lienard_regions["paper"].best_for(0.0, 0.0)
    rng = np.random.default_rng(1)

    def last_bits(P):
        P = P.copy()
        for _ in range(3):
            i, j = rng.integers(0, P.shape[0], 2)
            P[i, j] = np.nextafter(P[i, j], np.inf if rng.random() < 0.5 else -np.inf)
        return (P + P.T) / 2

    for gamma in (1e-8, 1e-5):
        seen = set()
        for t in range(6):
            c = cert if t == 0 else dataclasses.replace(cert, P0=last_bits(cert.P0), P1=last_bits(cert.P1))
            r = theorem2(lienard, p, c, gamma, (0.0, 0.0, 0.0, 0.0))
            assert r.holds and r.E0_bound > 0
            seen.add(tuple(f"{v:.9g}" for v in (r.s, r.eps, r.eta0, r.eta1, r.mu0, r.mu1, r.E0_bound)))
        assert len(seen) == 1, (gamma, seen)


def test_E0_bound_monotone_in_kappas(lienard, lienard_regions):
    """More initial attack energy never enlarges the guaranteed initial region."""
    p = plants.make("lienard")
    cert = lienard_regions["paper"].best_for(0.0, 0.0)
    pd = _PData.of(lienard, cert)
    lem = lemma_constants(lienard, RemainderRadius(p), 1e-4, 4.0)
    base = theorem2(lienard, p, cert, 1e-4, (0.0, 0.0, 0.0, 0.0))
    prev = math.inf
    for kF, kD in ((0, 0), (1, 0), (1, 0.1), (2, 0.1), (2, 0.5), (3, 1.0)):
        r = evaluate(lienard, pd, lem, cert, (kF, 0.0, kD, 0.0), base.s, base.eps, base.eta0, base.eta1)
        assert r.E0_bound <= prev
        prev = r.E0_bound


def test_theorem2_fails_outside_theorem1(lienard, lienard_regions):
    p = plants.make("lienard")
    cert = lienard_regions["paper"].best_area()
    r = theorem2(lienard, p, cert, 1e-6, (1.0, 5.0, 1.0, 0.5))
    assert not r.holds and r.E0_bound == 0.0


# ----------------------------------------------------------------------------- periodic schedule within budget
@settings(max_examples=80, deadline=None)
@given(rF=st.floats(0.05, 3.0), rD=st.floats(0.0, 0.9), kF=st.floats(0.0, 3.0), kD=st.floats(0.0, 2.0))
def test_periodic_within_budget_satisfies_assumptions(rF, rD, kF, kD):
    from attackers import check, make_schedule
    from testbed.analysis.sweep import periodic_within_budget

    pp = periodic_within_budget(rF, rD, kF, kD)
    assert pp["period"] == pytest.approx(1 / rF) and pp["length"] == pytest.approx(rD / rF)
    H = 40.0 / rF
    sch = make_schedule("periodic", pp, T=0.1, horizon=H)
    rep = check(sch, rF, rD, H)
    assert rep.kappa_F_min <= kF + 1e-9 and rep.kappa_D_min <= kD + 1e-9
    # and it uses the average rates over the 40 periods: N(H) / H = rho_F up to the one interval the horizon
    # may cut, |A(H)| / H = rho_D up to one sample T per interval (the sampling) and one period (the cut)
    assert len(sch) >= 39
    assert abs(sch.count(H) / H - rF) <= 1 / H + 1e-12
    assert abs(sch.union_length(H) / H - rD) <= (0.1 * len(sch) + 1 / rF) / H


def test_periodic_undefined_without_frequency():
    from testbed.analysis.sweep import periodic_within_budget

    assert periodic_within_budget(0.0, 0.2, 1.0, 0.5) is None


def test_e0_levels():
    from testbed.analysis.sweep import e0_levels

    X = np.array([[0.05, 0.0], [0.1, -0.3], [2.0, 1.0]])
    E = e0_levels(X, 0.1)
    assert E[0] == 0.1
    assert E[1] >= 0.3 and E[1] < 0.3 * 1.25 + 1e-12
    assert E[2] >= 2.0 and E[2] < 2.5 + 1e-12
    assert np.all(E >= np.max(np.abs(X), axis=1))          # Assumption 5
