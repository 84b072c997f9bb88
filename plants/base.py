"""Plant interface: dx/dt = f(x, u), equation (1) of the paper, with f(0, 0) = 0.

A plant is an immutable parameter object plus one numba-compiled right-hand side
``rhs(x, u, p, dx)`` written for a single state.  Everything else (the vectorized
``f`` over a batch, the flow map phi_T in ``testbed.loop.flow``, the batch simulator)
is built on that one function, so the model is written once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    import numpy.typing as npt

# numba is imported on first use, not here: a process that only reads a scenario (the
# launcher before it starts the nodes, the attacker) never pays its import (~0.3 s of CPU).


def _signature():
    """The one signature of every plant's right-hand side ``rhs(x, u, p, dx)``.  Plants compile
    it as a numba ``cfunc``; kernels receive it as a first-class function (a function
    pointer), so one compiled, cached kernel serves every plant."""
    import numba as nb

    arr = nb.types.float64[::1]
    return nb.types.void(arr, arr, arr, arr)


def __getattr__(name):  # ``RHS_SIG``, made on first use
    if name == "RHS_SIG":
        return _signature()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class RHS:
    """A plant's right-hand side compiled twice from one Python function.

    ``cfunc``: a C function pointer (numba ``cfunc``).  Kernels that receive it
    are compiled once for every plant and cached on disk across processes, so a
    command starts in a fraction of a second.  ``jit``: a numba dispatcher.
    Kernels that receive it are specialized for this plant (the right-hand side
    is inlined: about twice the speed), but numba cannot cache such a
    specialization across processes, so each process pays the compilation
    (seconds).  The batch simulator uses ``jit`` on request for big jobs.
    Both are made on first use.
    """

    def __init__(self, fn: Callable[..., None]) -> None:
        self.py = fn
        self.__name__ = fn.__name__
        self.__doc__ = fn.__doc__
        self._cfunc: Any = None  # numba's CFunc, made on first use
        self._jit: Any = None    # numba's Dispatcher, made on first use

    @property
    def jit(self) -> Any:
        """The numba dispatcher (``njit(cache=True, inline="always")``)."""
        if self._jit is None:
            import numba as nb

            self._jit = nb.njit(cache=True, inline="always")(self.py)
        return self._jit

    @property
    def cfunc(self) -> Any:
        """The compiled C function, made on first use: importing the bundled plants loads none of
        theirs (each costs tens of ms even from numba's disk cache), a process loads only its own."""
        if self._cfunc is None:
            import numba as nb

            self._cfunc = nb.cfunc(_signature(), cache=True)(self.py)
        return self._cfunc


def rhs_function(fn: Callable[..., None]) -> RHS:
    """Decorator for a plant's right-hand side: ``@rhs_function def my_rhs(x, u, p, dx): ...``."""
    return RHS(fn)


def _batch_rhs_py(rhs, x, u, p, out):
    for i in range(x.shape[0]):
        rhs(x[i], u[i], p, out[i])


_BATCH_RHS = None


def _batch_rhs(rhs, x, u, p, out):
    """f over a batch through the ``cfunc`` (compiled, or loaded from numba's cache, on first use)."""
    global _BATCH_RHS
    if _BATCH_RHS is None:
        import numba as nb

        _BATCH_RHS = nb.njit(cache=True)(_batch_rhs_py)
    _BATCH_RHS(rhs, x, u, p, out)


def broadcast_xu(x: npt.ArrayLike, u: npt.ArrayLike, n: int, m: int) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """States x (..., n) and inputs u (..., m) broadcast against each other's leading dimensions.

    Returns (lead, X, U): the common leading shape and C-contiguous float64 copies (B, n), (B, m), B the
    product of ``lead``; a batch kernel's input (``Plant.f``, ``testbed.loop.flow.phi_T``).
    """
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    X = np.array(np.broadcast_to(x, lead + (n,)), dtype=np.float64, order='C').reshape(-1, n)
    U = np.array(np.broadcast_to(u, lead + (m,)), dtype=np.float64, order='C').reshape(-1, m)
    return lead, X, U


@dataclass(frozen=True)
class Plant:
    """Base class of every plant.

    Subclasses are frozen dataclasses whose fields are the physical parameters.
    They set ``name``, ``rhs`` (a function ``rhs(x, u, p, dx)`` that writes
    f(x, u) into ``dx``, compiled with the ``rhs_function`` decorator), implement ``param_vector`` (the float64
    array ``p`` handed to ``rhs``), ``n``, ``m`` and ``linearization`` (the
    analytic A, B at the equilibrium), and state the region on which their
    Lipschitz bound is meant (``lipschitz_region``).
    """

    name: ClassVar[str] = ""
    rhs: ClassVar[Any] = None
    description: ClassVar[str] = ""
    #: the radius r of the box ||x||_inf <= r on which the plant's Lipschitz bound L
    #: (Assumption 1) is meant; inf: not stated (``testbed check-plant`` then uses a default)
    lipschitz_region: ClassVar[float] = float("inf")

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
        lead, xb, ub = broadcast_xu(x, u, self.n, self.m)
        out = np.empty_like(xb)
        _batch_rhs(type(self).rhs.cfunc, xb, ub, self.p, out)
        return out.reshape(lead + (self.n,))

    @property
    def A(self) -> np.ndarray:
        return self.linearization()[0]

    @property
    def B(self) -> np.ndarray:
        return self.linearization()[1]

    def jacobian_fd(self, x: npt.ArrayLike | None = None, u: npt.ArrayLike | None = None,
                    h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
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

    def input_gain(self, varrho: float, u_bound: float = 10.0, grid: int = 21, h: float = 1e-6) -> float:
        """Numerical estimate of L_u = sup ||df/du||_inf on the box of ``lipschitz``.

        How much the input can change f: ||f(x, u) - f(x, v)||_inf <= L_u ||u - v||_inf.
        The delay-aware quantizer rule uses it (``testbed.loop.quantizer.delay_margin_gain``).
        Plants affine in u with a constant input matrix B have L_u = ||B||_inf exactly
        and may override this; this default samples the box and is an estimate.
        """
        n, m = self.n, self.m
        if not math.isfinite(varrho):
            varrho = 10.0
        pts = grid if n <= 2 else max(3, int(round(grid ** (2 / n))))
        axes = [np.linspace(-varrho, varrho, pts)] * n + [np.linspace(-u_bound, u_bound, 5)] * m
        mesh = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n + m)
        X, U = mesh[:, :n], mesh[:, n:]
        rows = np.zeros((X.shape[0], n))
        for j in range(m):
            e = np.zeros(m)
            e[j] = h
            rows = rows + np.abs((self.f(X, U + e) - self.f(X, U - e)) / (2 * h))
        return float(rows.max())

    def remainder_gain(self, r: float, u_bound: float | None = None, grid: int | None = None) -> float:
        """Gain of the linearization remainder g on a box (used by Lemmas 1 and 2).

        Returns (an estimate of)

            G(r) = sup { ||g(x, u)||_inf / (||x||_inf + ||u||_inf) :
                         0 < ||x||_inf <= r, ||u||_inf <= u_bound }

        with u_bound = r by default.  The box contains the set
        sqrt(||x||_inf^2 + ||u||_inf^2) < r of the appendix proofs, so a bound on
        G(r) gives the radii d' (gain 1) and delta' (gain gamma) there.  G is
        nondecreasing in r.

        This default is NUMERICAL: the ratio is sampled on a grid over the box
        (about 2e5 points, at least 5 per axis) and the best samples are refined by
        a bounded local maximization.  It is an estimate, not a proof; plants with
        an explicit remainder override it with the exact supremum.
        """
        from scipy.optimize import minimize

        r = float(r)
        ub = r if u_bound is None else float(u_bound)
        if r <= 0.0:
            return 0.0
        n, m = self.n, self.m
        pts = grid or max(5, min(41, int(round(2e5 ** (1.0 / (n + m))))))
        axes = [np.linspace(-r, r, pts)] * n + [np.linspace(-ub, ub, pts if ub > 0 else 1)] * m
        Z = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n + m)

        def ratio(Zb):
            Zb = np.atleast_2d(Zb)
            X, U = Zb[:, :n], Zb[:, n:]
            den = np.max(np.abs(X), axis=1) + (np.max(np.abs(U), axis=1) if m else 0.0)
            num = np.max(np.abs(self.remainder(X, U)), axis=1)
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)

        vals = ratio(Z)
        best = float(vals.max())
        bounds = [(-r, r)] * n + [(-ub, ub)] * m
        for k in np.argsort(vals)[-8:]:
            res = minimize(lambda z: -float(ratio(z)[0]), Z[k], method="L-BFGS-B", bounds=bounds)
            best = max(best, -float(res.fun))
        return best


class PlantFault(RuntimeError):
    """The true plant failed while it ran (an FMU step that failed, a variable it lost), one line."""


@runtime_checkable
class PlantProcess(Protocol):
    """The true plant as a process that is stepped in time: what the simulator and the live plant node hold.

    A plant of equation (1) integrated by ``testbed.loop.flow`` and a co-simulation FMU
    (``plants.fmu.FMUPlant``) both present it.  Between sampling instants the input
    u is held (zero-order hold), so one sampling period is ``advance(u_k, T)``; a
    delayed actuation splits the period into two ``advance`` calls.

    Members
    -------
    n, m : int
        State and input dimensions.
    reset(x0)
        (Re)initialize at state x0, time 0 (an FMU: instantiate, set the state
        variables in initialization mode, exit initialization mode).
    advance(u, dt) -> int
        Hold u for dt seconds; returns 0 when the step succeeded, raises
        ``PlantFault`` when it did not.  dt = 0 is a no-op.
    x : np.ndarray
        A copy of the current state.
    close()
        Release what the plant holds (an FMU instance, its library, its files).
    """

    n: int
    m: int

    def reset(self, x0: np.ndarray) -> None: ...

    def advance(self, u: np.ndarray, dt: float) -> int: ...

    @property
    def x(self) -> np.ndarray: ...

    def close(self) -> None: ...
