"""Contract test over every registered plant, and the Lienard plant of the paper."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

import plants

ALL = plants.names()


@pytest.mark.parametrize("name", ALL)
def test_contract(name):
    p = plants.make(name)
    n, m = p.n, p.m
    assert n >= 1 and m >= 1
    # equilibrium at the origin
    assert_allclose(p.f(p.x_eq, p.u_eq), np.zeros(n), atol=1e-14)
    # vectorized f over a batch equals f one by one, shapes right, finite, repeatable
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.5, 0.5, (64, n))
    U = rng.uniform(-1, 1, (64, m))
    F = p.f(X, U)
    assert F.shape == (64, n)
    assert np.all(np.isfinite(F))
    for i in range(0, 64, 7):
        assert_allclose(p.f(X[i], U[i]), F[i], rtol=0, atol=0)
    assert_allclose(p.f(X, U), F, rtol=0, atol=0)
    # broadcast: one state, many inputs
    assert p.f(X[0], U).shape == (64, n)
    # linearization against central finite differences
    A, B = p.linearization()
    assert A.shape == (n, n) and B.shape == (n, m)
    Jx, Ju = p.jacobian_fd()
    assert_allclose(A, Jx, atol=1e-6)
    assert_allclose(B, Ju, atol=1e-6)
    # remainder g vanishes faster than linearly at the origin
    x = np.full(n, 1e-3)
    u = np.full(m, 1e-3)
    assert np.max(np.abs(p.remainder(x, u))) <= 1e-4 * 1e-3
    # the origin of the linearization is unstable for the bundled nonlinear plants
    if name != "linear":
        assert np.max(np.linalg.eigvals(A).real) > 0
    # Lipschitz estimate is positive and finite on a small box
    L = p.lipschitz(0.2, u_bound=1.0, grid=9)
    assert 0 < L < np.inf


def test_registry_errors():
    with pytest.raises(ValueError, match="unknown plant 'nope'.*lienard"):
        plants.make("nope")
    with pytest.raises(ValueError, match="unknown parameter.*'c'"):
        plants.make("lienard", c=1.0)
    with pytest.raises(ValueError, match="must be > 0"):
        plants.make("pendulum", l=0.0)
    with pytest.raises(ValueError, match="square"):
        plants.make("linear", A=[[1.0, 2.0]], B=[[1.0]])


def test_lienard_is_the_paper_plant():
    p = plants.make("lienard", a=1 / 3, b=1 / 50)
    x = np.array([0.7, -0.2])
    a, b = 1 / 3, 1 / 50
    assert_allclose(p.f(x, [0.3]), [x[1] + x[0] + a * x[0] ** 3 - b * x[0] ** 5, -x[0] + 0.3], rtol=1e-15)
    # the paper's L = 10 holds on a region larger than the nominal region of attraction
    assert p.lipschitz(p.lipschitz_region, grid=81) <= 10.0
    assert p.lipschitz(5.0, grid=81) > 10.0


def test_cartpole_has_n4():
    p = plants.make("cartpole")
    assert (p.n, p.m) == (4, 1)
