"""The flow map phi_T(x, u): the solution of x' = f(x, u) at time T under a held input.

Section II.A of the paper defines phi(t, x, u) for a constant input and
phi_T(x, u) := phi(T, x, u).  The plant, the encoder's and decoder's predictions
(update rule (xi)) and the analysis all call this one implementation.

Integrator: an adaptive explicit Runge-Kutta 8(5,3) pair (Dormand-Prince, the
coefficients of scipy's DOP853, unrolled in ``_dop853.py``) compiled with numba.  Adaptivity keeps it finite
and accurate when a long attack drives the state and input far from the origin
(then the -b x1^5 term of the Lienard plant is stiff for a fixed-step explicit
method); divergence is reported as a status code, never as NaN:

    FLOW_OK          the step finished within tolerance
    FLOW_DIVERGED    ||x||_inf exceeded ``x_max``; the returned state is the
                     last accepted one (finite)
    FLOW_STEP_LIMIT  more than ``max_steps`` steps (or the step size underflowed);
                     the returned state is the last accepted one (finite)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numba as nb
import numpy as np

from plants.base import broadcast_xu

from ._dop853 import dop853_step
from .params import DEFAULT_FLOW, FLOW_DIVERGED, FLOW_OK, FLOW_STEP_LIMIT, STATUS_NAMES, FlowOptions  # noqa: F401 - flow.py names them for its callers

if TYPE_CHECKING:
    from plants.base import Plant


@nb.njit(cache=True)
def flow_into(rhs: Any, x0: np.ndarray, u: np.ndarray, p: np.ndarray, T: float, opts: np.ndarray, K: np.ndarray,
              ytmp: np.ndarray, out: np.ndarray) -> int:
    """phi_T(x0, u) written into ``out``; returns a FLOW_* status.

    K (13 x n) and ytmp (n,) are scratch arrays so that batch loops allocate nothing.
    """
    rtol = opts[0]
    atol = opts[1]
    x_max = opts[2]
    max_steps = int(opts[3])
    n = x0.shape[0]
    for i in range(n):
        out[i] = x0[i]
    if T <= 0.0:
        return 0
    t = 0.0
    h = T
    rhs(out, u, p, K[0])
    steps = 0
    while t < T:
        if steps >= max_steps:
            return 2
        last = False
        if t + h >= T:
            h = T - t
            last = True
        err = dop853_step(rhs, out, u, p, h, K, ytmp, rtol, atol)
        steps += 1
        if err <= 1.0:  # accept (err is NaN for a non-finite trial step: rejected)
            t = T if last else t + h
            big = 0.0
            for i in range(n):
                out[i] = ytmp[i]
                K[0, i] = K[12, i]
                big = max(big, abs(ytmp[i]))
            if not big <= x_max:
                return 1
            if last:
                break
            fac = 10.0 if err == 0.0 else min(10.0, 0.9 * err ** (-1.0 / 8.0))
            h = h * fac
        else:
            fac = 0.2
            if err == err:  # not NaN
                fac = max(0.2, 0.9 * err ** (-1.0 / 8.0))
            h = h * fac
            if h < 1e-15 * T:
                return 2
    return 0


@nb.njit(cache=True)
def flow_batch_kernel(rhs: Any, X: np.ndarray, U: np.ndarray, p: np.ndarray, T: float, opts: np.ndarray,
                      out: np.ndarray, status: np.ndarray) -> None:
    n = X.shape[1]
    K = np.empty((13, n))
    ytmp = np.empty(n)
    for b in range(X.shape[0]):
        status[b] = flow_into(rhs, X[b], U[b], p, T, opts, K, ytmp, out[b])


def compiled_for(dispatcher: Any, args: tuple) -> Callable[..., Any]:
    """The compiled overload of a numba ``dispatcher`` for the types of ``args`` (call it once first).

    Calling it skips numba's type dispatch of every call, which costs about 20 us when an
    argument is a function pointer (a plant's ``cfunc``): more than the flow map over a
    short period, on the path of every live sample.  The same machine code, so the same
    numbers.  The dispatcher itself where the overload is not found.
    """
    try:
        return dispatcher.overloads[tuple(nb.typeof(a) for a in args)].entry_point
    except Exception:  # noqa: BLE001 - an internal of numba: fall back to the ordinary call
        return dispatcher


def phi_T(plant: Plant, x: np.ndarray, u: np.ndarray, T: float,
          opts: FlowOptions = DEFAULT_FLOW) -> tuple[np.ndarray, np.ndarray]:
    """Flow map phi_T(x, u) over a batch.

    Parameters
    ----------
    plant : plants.Plant
    x : array (..., n) initial states
    u : array (..., m) held inputs, broadcast against x
    T : horizon (the sampling period)

    Returns
    -------
    (x_T, status) : array (..., n) and int8 array (...) of FLOW_* codes.  x_T is
    always finite: for a diverged trajectory it is the last accepted state.
    """
    lead, X, U = broadcast_xu(x, u, plant.n, plant.m)
    out = np.empty_like(X)
    status = np.empty(X.shape[0], dtype=np.int8)
    flow_batch_kernel(type(plant).rhs.cfunc, X, U, plant.p, float(T), opts.as_array(), out, status)
    return out.reshape(lead + (plant.n,)), status.reshape(lead)
