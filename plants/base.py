"""Plant interface: dx/dt = f(x, u), equation (1) of the paper, with f(0, 0) = 0.

A plant is an immutable parameter object plus one numba-compiled right-hand side
``rhs(x, u, p, dx)`` written for a single state.  Everything else (the vectorized
``f`` over a batch, the flow map phi_T in ``testbed.flow``, the batch simulator)
is built on that one function, so the model is written once.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _batch_rhs(rhs, x, u, p, out):
    for i in range(x.shape[0]):
        rhs(x[i], u[i], p, out[i])


@dataclass(frozen=True)
class Plant:
    """Base class of every plant.

    Subclasses are frozen dataclasses whose fields are the physical parameters.
    They set ``name``, ``rhs`` (numba ``njit`` function ``rhs(x, u, p, dx)``
    that writes f(x, u) into ``dx``), implement ``param_vector`` (the float64
    array ``p`` handed to ``rhs``), ``n``, ``m`` and ``linearization`` (the
    analytic A, B at the equilibrium), and state the region on which their
    Lipschitz bound is meant (``lipschitz_region``).
    """

    name: ClassVar[str] = ""
    rhs: ClassVar[Any] = None
    description: ClassVar[str] = ""

    # -- to be provided by subclasses -------------------------------------------------
    @property
    def n(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def m(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def param_vector(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def linearization(self) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
        """Analytic A = df/dx(0, 0), B = df/du(0, 0) (Section III.A)."""
        raise NotImplementedError

    # -- shared machinery -------------------------------------------------------------
    @property
    def p(self) -> np.ndarray:
        return self.param_vector()

    @property
    def x_eq(self) -> np.ndarray:
        """Equilibrium state (the origin: plants are written in shifted coordinates)."""
        return np.zeros(self.n)

    @property
    def u_eq(self) -> np.ndarray:
        return np.zeros(self.m)

    def params_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Vectorized right-hand side f(x, u).

        Parameters
        ----------
        x : array (..., n)
        u : array (..., m), broadcast against x's leading dimensions.

        Returns
        -------
        array (..., n), float64.
        """
        x = np.asarray(x, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        xb = np.ascontiguousarray(np.broadcast_to(x, lead + (self.n,))).reshape(-1, self.n)
        ub = np.ascontiguousarray(np.broadcast_to(u, lead + (self.m,))).reshape(-1, self.m)
        out = np.empty_like(xb)
        _batch_rhs(type(self).rhs, xb, ub, self.p, out)
        return out.reshape(lead + (self.n,))

    @property
    def A(self) -> np.ndarray:
        return self.linearization()[0]

    @property
    def B(self) -> np.ndarray:
        return self.linearization()[1]

    def jacobian_fd(self, x=None, u=None, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Central finite-difference Jacobians (df/dx, df/du) at (x, u); default the equilibrium."""
        x = self.x_eq if x is None else np.asarray(x, dtype=np.float64)
        u = self.u_eq if u is None else np.asarray(u, dtype=np.float64)
        ex = np.eye(self.n) * h
        eu = np.eye(self.m) * h
        Jx = (self.f(x + ex, np.broadcast_to(u, (self.n, self.m)))
              - self.f(x - ex, np.broadcast_to(u, (self.n, self.m)))).T / (2 * h)
        Ju = (self.f(np.broadcast_to(x, (self.m, self.n)), u + eu)
              - self.f(np.broadcast_to(x, (self.m, self.n)), u - eu)).T / (2 * h)
        return Jx, Ju

    def remainder(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The paper's g(x, u) = f(x, u) - A x - B u, remainder of the linearization (3).

        Named ``remainder`` because several plants have a parameter called g (gravity).
        """
        A, B = self.linearization()
        x = np.asarray(x, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        return self.f(x, u) - x @ A.T - u @ B.T

    def lipschitz(self, varrho: float, u_bound: float = 10.0, grid: int = 41,
                  h: float = 1e-6) -> float:
        """Numerical estimate of the Lipschitz constant L of Assumption 1.

        sup of the induced infinity norm of df/dx over the box
        D = {||x||_inf <= varrho} x {||u||_inf <= u_bound}, sampled on a grid with
        ``grid`` points per axis (coarser for n > 2).  For plants affine in u the
        u range does not matter.  This is an estimate from samples, not a proof.
        """
        n, m = self.n, self.m
        pts = grid if n <= 2 else max(5, int(round(grid ** (2 / n))))
        axes = [np.linspace(-varrho, varrho, pts)] * n + [np.linspace(-u_bound, u_bound, 5)] * m
        mesh = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n + m)
        X, U = mesh[:, :n], mesh[:, n:]
        best = 0.0
        for j in range(n):
            e = np.zeros(n)
            e[j] = h
            col = (self.f(X + e, U) - self.f(X - e, U)) / (2 * h)  # d f / d x_j, shape (P, n)
            if j == 0:
                rows = np.abs(col)
            else:
                rows = rows + np.abs(col)
        best = float(rows.max())
        return best
