"""Controller design: exact zero-order-hold discretization and discrete LQR (Section III.A).

    A~ = e^{A T},   B~ = int_0^T e^{A s} ds B

computed exactly with the block-matrix exponential expm([[A, B], [0, 0]] T).
K is chosen so that A~ + B~ K is Schur stable; the paper's gain
K = [-1.81 -1.90] for the Lienard plant is the discrete LQR gain with
T = 0.1, Q = 1e-4 I, R = 1.
"""

from __future__ import annotations

import numpy as np


def c2d(A: np.ndarray, B: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretization (A~, B~) of (A, B) with sampling period T."""
    A = np.atleast_2d(np.asarray(A, dtype=float))
    B = np.asarray(B, dtype=float).reshape(A.shape[0], -1)
    from scipy.linalg import expm  # here, not at import: a live node loading a scenario needs no scipy

    n, m = B.shape
    Mx = np.zeros((n + m, n + m))
    Mx[:n, :n] = A
    Mx[:n, n:] = B
    E = expm(Mx * T)
    return E[:n, :n], E[:n, n:]


def dlqr(Ad: np.ndarray, Bd: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Discrete LQR gain with the sign convention u = K x (so A~ + B~ K is Schur).

    Minimizes sum x'Qx + u'Ru; K = -(R + B'PB)^{-1} B'PA with P the DARE solution.
    """
    from scipy.linalg import solve_discrete_are

    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    R = np.atleast_2d(np.asarray(R, dtype=float))
    P = solve_discrete_are(Ad, Bd, Q, R)
    return -np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)


def spectral_radius(M: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(np.atleast_2d(M)))))


def closed_loop(Ad: np.ndarray, Bd: np.ndarray, K: np.ndarray) -> np.ndarray:
    """A~ + B~ K."""
    return Ad + Bd @ np.asarray(K, dtype=float).reshape(Bd.shape[1], Ad.shape[0])
