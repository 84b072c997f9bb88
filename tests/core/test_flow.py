"""The flow map phi_T: accuracy, batch = one by one, stiffness after long attacks, divergence as data."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.integrate import solve_ivp

import plants
from testbed.loop.flow import FLOW_DIVERGED, FLOW_OK, FlowOptions, phi_T


def _ref(p, x0, u, T, method="DOP853"):
    sol = solve_ivp(lambda t, x: p.f(x, u), (0, T), x0, method=method, rtol=1e-13, atol=1e-15)
    return sol.y[:, -1]


@pytest.mark.parametrize("name", plants.names())
def test_accuracy_against_tight_reference(name):
    p = plants.make(name)
    rng = np.random.default_rng(1)
    X = rng.uniform(-0.5, 0.5, (20, p.n))
    U = rng.uniform(-1, 1, (20, p.m))
    Y, st = phi_T(p, X, U, 0.1)
    assert np.all(st == FLOW_OK)
    for i in range(20):
        assert_allclose(Y[i], _ref(p, X[i], U[i], 0.1), atol=1e-9, rtol=0)


def test_batch_equals_single_and_is_deterministic():
    p = plants.make("lienard")
    rng = np.random.default_rng(2)
    X = rng.uniform(-2, 2, (50, 2))
    U = rng.uniform(-5, 5, (50, 1))
    Y, _ = phi_T(p, X, U, 0.1)
    for i in range(50):
        yi, _ = phi_T(p, X[i], U[i], 0.1)
        assert np.array_equal(yi, Y[i])
    assert np.array_equal(phi_T(p, X, U, 0.1)[0], Y)


@pytest.mark.parametrize("x0,u", [([5.0, 50.0], 400.0), ([100.0, 100.0], -400.0),
                                  ([-30.0, 2.0], 0.0), ([3.0, -200.0], 370.0)])
@pytest.mark.slow  # seconds of numerics: long stiff integrations
def test_stiff_after_long_attack(x0, u):
    """After a 1 s attack E_k ~ 100 and K q_k is huge: the -b x1^5 term is stiff; stay finite and accurate."""
    p = plants.make("lienard")
    y, st = phi_T(p, np.array(x0), np.array([u]), 0.1)
    assert st == FLOW_OK
    assert np.all(np.isfinite(y))
    ref = _ref(p, np.array(x0), np.array([u]), 0.1, method="Radau")
    assert_allclose(y, ref, rtol=1e-7, atol=1e-7)


def test_fixed_step_rk4_would_blow_up():
    """The reason for adaptivity: classic RK4 with 10 steps per T gives NaN/inf here."""
    p = plants.make("lienard")
    x = np.array([100.0, 100.0])
    u = np.array([-400.0])
    h = 0.01
    with np.errstate(all="ignore"):
        for _ in range(10):
            k1 = p.f(x, u)
            k2 = p.f(x + h / 2 * k1, u)
            k3 = p.f(x + h / 2 * k2, u)
            k4 = p.f(x + h * k3, u)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    assert not np.all(np.isfinite(x))


def test_divergence_is_data_not_nan():
    p = plants.make("linear", A=[[50.0, 0.0], [0.0, 1.0]], B=[[1.0], [0.0]])
    y, st = phi_T(p, np.array([1.0, 1.0]), np.array([0.0]), 1.0, FlowOptions(x_max=1e6))
    assert st == FLOW_DIVERGED
    assert np.all(np.isfinite(y))
    # the finite-escape-time ODE x' = x^5 (Lienard x1 with a = b = 0 flipped) also reports, never NaN
    q = plants.make("lienard", a=0.0, b=-1.0)
    y, st = phi_T(q, np.array([3.0, 0.0]), np.array([0.0]), 1.0)
    assert st != FLOW_OK
    assert np.all(np.isfinite(y))


def test_a_state_decayed_to_the_bottom_of_the_doubles_still_flows():
    """Near 1e-163 the embedded error terms underflow to 0 one at a time: the step is exact, not 0 / 0.

    A converging run at T = 1 ms gets there within about 20 minutes (E_k and x_k shrink by
    Lambda / M every sample); this used to end it with a ZeroDivisionError.
    """
    from plants.lienard import Lienard

    pl = Lienard()
    for e in np.linspace(-150, -320, 681):
        for v in ([1.0, 1.0], [1.0, -0.3], [0.2, 1.0]):
            x = np.array(v) * 10.0 ** e
            y, status = phi_T(pl, x, np.zeros(1), 0.001)
            assert status == FLOW_OK and np.all(np.isfinite(y)) and np.max(np.abs(y)) <= 2 * np.max(np.abs(x)) + 1e-320, (e, v, y)
