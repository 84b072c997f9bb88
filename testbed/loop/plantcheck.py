"""The contract a plant of equation (1) must meet, checked one verdict at a time.

Used by the contract test over every registered plant (``tests/core/test_plants.py``)
and by ``testbed check-plant REF`` on a user's plant:

* ``shapes``: n, m >= 1; f over a batch has shape (P, n), is finite, equals f
  point by point and broadcasts one state against many inputs; A is n x n, B n x m;
* ``equilibrium``: f(0, 0) = 0 (the plant is written in shifted coordinates);
* ``jacobian``: the analytic A = df/dx(0, 0), B = df/du(0, 0) (``linearization``)
  against central finite differences (``Plant.jacobian_fd``);
* ``remainder``: g(x, u) = f - A x - B u vanishes faster than linearly at the origin (3);
* ``lipschitz``: the numerical estimate of Assumption 1's L on ||x||_inf <= r
  (``Plant.lipschitz``) against the stated L;
* ``assumption2``: M > Lambda = e^{L T};
* ``stabilizable``: (A, B) stabilizable (PBH test on the eigenvalues with Re >= 0)
  and so is its ZOH discretization (A~, B~) at T (``testbed.loop.control.c2d``; on
  |lambda| >= 1), which the LQR design and Theorem 1 need.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from .control import c2d

if TYPE_CHECKING:
    from plants.base import Plant

#: defaults when no scenario is given: the paper's T and M
DEFAULT_T = 0.1
DEFAULT_M = 6
DEFAULT_REGION = 1.0
DEFAULT_U_BOUND = 10.0


@dataclass(frozen=True)
class Check:
    name: str
    ok: bool
    detail: str

    def to_dict(self) -> dict:
        return asdict(self)


def _pbh_ok(A: np.ndarray, B: np.ndarray, unstable: Callable[[complex], bool]) -> tuple[bool, list]:
    """PBH: rank [A - lambda I, B] = n for every eigenvalue lambda with ``unstable(lambda)``."""
    n = A.shape[0]
    bad = []
    scale = max(1.0, float(np.abs(A).max()), float(np.abs(B).max()))
    for lam in np.linalg.eigvals(A):
        if not unstable(lam):
            continue
        Mx = np.hstack([A - lam * np.eye(n), B])
        s = np.linalg.svd(Mx, compute_uv=False)   # n singular values: rank n iff the n-th is > 0
        if s[n - 1] <= 1e-9 * scale:
            bad.append(complex(lam))
    return not bad, bad


def _fmt_l(lam: complex) -> str:
    return f"{lam.real:.4g}" if abs(lam.imag) < 1e-12 else f"{lam.real:.4g}{lam.imag:+.4g}j"


def check_plant(plant: Plant, *, L: float | None = None, T: float = DEFAULT_T, M: int = DEFAULT_M,
                region: float | None = None, u_bound: float = DEFAULT_U_BOUND, grid: int = 41,
                seed: int = 0) -> list[Check]:
    """Every check of the module docstring on one plant instance, in order.

    Parameters
    ----------
    plant : plants.Plant
    L : the Lipschitz constant the quantizer is designed with ([quantizer] L);
        None: the estimate itself is used for Assumption 2 (and the lipschitz
        check only reports it).
    T, M : sampling period and quantizer levels of Assumption 2.
    region : r of the box ||x||_inf <= r of the Lipschitz estimate; None: the
        plant's ``lipschitz_region`` when finite, else ``DEFAULT_REGION``.
    u_bound : ||u||_inf bound of that box.

    Returns
    -------
    list of ``Check`` (name, ok, one-line detail).  Later checks that need an
    earlier one that failed (shapes) are reported as failed with the reason.
    """
    out: list[Check] = []
    rng = np.random.default_rng(seed)
    # ---- shapes
    try:
        n, m = int(plant.n), int(plant.m)
        if n < 1 or m < 1:
            raise ValueError(f"n = {n}, m = {m}: both must be >= 1")
        X = rng.uniform(-0.5, 0.5, (64, n))
        U = rng.uniform(-1.0, 1.0, (64, m))
        F = np.asarray(plant.f(X, U))
        if F.shape != (64, n):
            raise ValueError(f"f over a batch of 64 has shape {F.shape}, expected (64, {n})")
        if not np.all(np.isfinite(F)):
            raise ValueError("f is not finite on |x| <= 0.5, |u| <= 1")
        for i in range(0, 64, 7):
            if not np.array_equal(np.asarray(plant.f(X[i], U[i])), F[i]):
                raise ValueError(f"f(x_i, u_i) one by one differs from the batch at i = {i}")
        if not np.array_equal(np.asarray(plant.f(X, U)), F):
            raise ValueError("f is not repeatable: two calls on the same batch differ")
        if np.asarray(plant.f(X[0], U)).shape != (64, n):
            raise ValueError("f does not broadcast one state against a batch of inputs")
        A, B = (np.asarray(a, dtype=float) for a in plant.linearization())
        if A.shape != (n, n) or B.shape != (n, m):
            raise ValueError(f"linearization gives A {A.shape}, B {B.shape}; expected ({n}, {n}), ({n}, {m})")
    except Exception as e:  # noqa: BLE001 - a user's plant may raise anything: the verdict says what
        out.append(Check("shapes", False, f"{type(e).__name__}: {e}" if not isinstance(e, ValueError) else str(e)))
        return out + [Check(c, False, "not checked: shapes failed")
                      for c in ("equilibrium", "jacobian", "remainder", "lipschitz", "assumption2", "stabilizable")]
    out.append(Check("shapes", True, f"n = {n}, m = {m}; f vectorized, finite, repeatable, broadcasts; "
                                     f"A {n}x{n}, B {n}x{m}"))
    # ---- equilibrium
    f0 = np.asarray(plant.f(np.zeros(n), np.zeros(m)), dtype=float)
    e0 = float(np.abs(f0).max())
    out.append(Check("equilibrium", e0 <= 1e-12, f"||f(0, 0)||_inf = {e0:.3g}" + ("" if e0 <= 1e-12 else
                                                                                      " (must be 0: write the plant in "
                                                                                      "coordinates shifted to its equilibrium)")))
    # ---- jacobian
    Jx, Ju = plant.jacobian_fd()
    tolA = 1e-6 * max(1.0, float(np.abs(Jx).max()))
    tolB = 1e-6 * max(1.0, float(np.abs(Ju).max()))
    eA, eB = float(np.abs(A - Jx).max()), float(np.abs(B - Ju).max())
    ok = eA <= tolA and eB <= tolB
    det = f"max |A - A_fd| = {eA:.2e} (tol {tolA:.0e}), max |B - B_fd| = {eB:.2e} (tol {tolB:.0e})"
    if not ok:
        det += f"; finite differences give A = {np.round(Jx, 6).tolist()}, B = {np.round(Ju, 6).tolist()}"
    out.append(Check("jacobian", ok, det))
    # ---- remainder o(|x| + |u|)
    x, u = np.full(n, 1e-3), np.full(m, 1e-3)
    g = float(np.abs(plant.remainder(x, u)).max())
    out.append(Check("remainder", g <= 1e-7, f"||g(x, u)||_inf = {g:.2e} at ||x||, ||u|| = 1e-3 (must be "
                                              "o(1e-3): <= 1e-7)"))
    # ---- lipschitz
    r = region
    if r is None:
        lr = getattr(plant, "lipschitz_region", None)
        r = float(lr) if lr is not None and math.isfinite(lr) and lr > 0 else DEFAULT_REGION
    L_est = float(plant.lipschitz(r, u_bound=u_bound, grid=grid))
    where = f"on ||x||_inf <= {r:g}, ||u||_inf <= {u_bound:g}"
    if not math.isfinite(L_est):
        out.append(Check("lipschitz", False, f"estimate of L is not finite {where}"))
    elif L is None:
        out.append(Check("lipschitz", True, f"estimate L = {L_est:.4g} {where} (no [quantizer] L given: "
                                            "Assumption 2 below uses the estimate)"))
    else:
        out.append(Check("lipschitz", L_est <= L, f"estimate L = {L_est:.4g} {where} "
                                                  + ("<=" if L_est <= L else "EXCEEDS") + f" stated L = {L:g}"))
    # ---- Assumption 2
    L2 = L_est if L is None else float(L)
    Lam = math.exp(L2 * T) if math.isfinite(L2) else math.inf
    out.append(Check("assumption2", M > Lam, f"M = {M} {'>' if M > Lam else '<='} Lambda = e^(L T) = {Lam:.4g} "
                                             f"(L = {L2:.4g}, T = {T:g} s)"))
    # ---- stabilizability
    okc, badc = _pbh_ok(A, B, lambda lam: lam.real >= 0.0)
    Ad, Bd = c2d(A, B, T)
    okd, badd = _pbh_ok(Ad, Bd, lambda lam: abs(lam) >= 1.0)
    eig = ", ".join(_fmt_l(complex(v)) for v in np.linalg.eigvals(A))
    if okc and okd:
        det = f"(A, B) and (A~, B~) at T = {T:g} s are stabilizable; eig(A) = {eig}"
    else:
        det = "; ".join(([f"(A, B) not stabilizable: uncontrollable eigenvalue(s) {', '.join(map(_fmt_l, badc))}"]
                         if not okc else [])
                        + ([f"(A~, B~) at T = {T:g} s not stabilizable: uncontrollable eigenvalue(s) "
                            f"{', '.join(map(_fmt_l, badd))}"] if not okd else []))
    out.append(Check("stabilizable", okc and okd, det))
    return out


__all__ = ["Check", "check_plant", "DEFAULT_T", "DEFAULT_M", "DEFAULT_REGION", "DEFAULT_U_BOUND"]
