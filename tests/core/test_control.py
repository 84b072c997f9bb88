import numpy as np
from numpy.testing import assert_allclose
from scipy.integrate import solve_ivp

import plants
from testbed.loop.control import c2d, closed_loop, dlqr, spectral_radius


def test_paper_gain_reproduced():
    """Discrete LQR on (A~, B~), T = 0.1, Q = 1e-4 I, R = 1 gives the paper's K = [-1.81 -1.90]."""
    p = plants.make("lienard")
    Ad, Bd = c2d(p.A, p.B, 0.1)
    K = dlqr(Ad, Bd, 1e-4 * np.eye(2), np.eye(1))
    assert_allclose(K, [[-1.81, -1.90]], atol=0.005)
    assert spectral_radius(closed_loop(Ad, Bd, K)) < 1
    assert spectral_radius(Ad) > 1


def test_c2d_is_exact_zoh():
    A = np.array([[0.0, 1.0], [2.0, -0.5]])
    B = np.array([[0.0], [1.0]])
    T = 0.3
    Ad, Bd = c2d(A, B, T)
    for x0, u in [([1.0, 0.0], 0.0), ([0.0, 1.0], 0.0), ([0.0, 0.0], 1.0)]:
        sol = solve_ivp(lambda t, x, u=u: A @ x + B[:, 0] * u, (0, T), x0, rtol=1e-12, atol=1e-14)
        assert_allclose(sol.y[:, -1], Ad @ np.array(x0) + Bd[:, 0] * u, atol=1e-10)
