"""Theorem 1: the allowable average DoS frequency and duration (condition (stability)).

Notation of the paper, Section IV.A-B.  With Phi_0 := A~ + B~ K and Phi_1 := A~
(the closed loop and the open loop over one sampling period T), choose

    phi_0 in (rho(Phi_0)^2, 1),   phi_1 in (max(1, rho(Phi_1)^2), inf)

(so that phi_p^{-1/2} Phi_p is Schur) and positive definite P_0, P_1 with

    Phi_0' P_0 Phi_0 - phi_0 P_0 < 0,       (Lyapunov_inequality1)
    Phi_1' P_1 Phi_1 - phi_1 P_1 < 0.       (Lyapunov_inequality2)

Then, with eta_0, eta_1 > 0 (W_p of (Lyapunov_function)),

    mu_0 = max{lambda_max(P_1) / lambda_min(P_0), eta_1 / eta_0}     (mu0)
    mu_1 = max{lambda_max(P_0) / lambda_min(P_1), eta_0 / eta_1}     (mu1)
    nu_0 = max{phi_0, Lambda^2 / M^2},  nu_1 = max{phi_1, Lambda^2}  (nu0), (nu1)

and the origin is locally asymptotically stable under every DoS attack of
Assumptions 3 and 4 with

    rho_F T ln(mu_0 mu_1) + (1 - rho_D*) ln nu_0 + rho_D* ln nu_1 < 0,   (stability)

rho_D* = rho_D + rho_F T.  Writing a = ln(mu_0 mu_1) >= 0, b = -ln nu_0 > 0 and
c = ln nu_1 > 0, (stability) reads  rho_D (b + c) + rho_F T (a + b + c) < b:  for one
choice of (phi, P, eta) the allowable set is the triangle under the line through

    rho_D_max = b / (b + c)   (rho_F = 0)  and   rho_F_max = b / (T (a + b + c))  (rho_D = 0).

What this module optimizes.  Theorem 1 holds as soon as ONE admissible choice
satisfies (stability), so the allowable region is the union of the triangles of all
choices and its boundary is their upper envelope

    rho_F^max(rho_D) = sup over (phi_0, phi_1, P_0, P_1, eta) of (b - rho_D (b + c)) / (T (a + b + c)).

* eta_0, eta_1 enter only through eta_1 / eta_0; any ratio in
  [lambda_min(P_1) / lambda_max(P_0), lambda_max(P_1) / lambda_min(P_0)] leaves the
  eigenvalue ratios in charge, and then mu_0 mu_1 = cond(P_0) cond(P_1)
  (cond = lambda_max / lambda_min) whatever the scaling of P_1 against P_0.
* So for fixed phis the best P_p minimizes cond(P_p) subject to its Lyapunov
  inequality: the LMI problem  min kappa  s.t.  I <= P <= kappa I,
  Phi' P Phi <= phi P  (solved by :mod:`testbed.analysis.lmi`).
* phi_1 <= Lambda^2 costs nothing (nu_1 = Lambda^2), and a larger phi_1 only
  enlarges the feasible set of P_1, so phi_1 is searched on [Lambda^2, 20 Lambda^2];
  phi_0 trades b (better when phi_0 is small) against cond(P_0) (worse), and is
  searched on a grid dense near its lower end max(rho(Phi_0)^2, Lambda^2 / M^2).
* The envelope is evaluated on a grid of rho_D; each boundary point comes with the
  explicit certificate (phi_0, phi_1, P_0, P_1, eta) that achieves it, so the drawn
  boundary is a certified inner approximation of the true one.

``rule="tight"`` replaces the sufficient constants (mu0), (mu1) by the smallest
constants with property (mu), W_1 <= mu_0 W_0 and W_0 <= mu_1 W_1:
mu_0 = max{lambda_max(P_0^{-1} P_1), eta_1 / eta_0} and symmetrically.  The proof of
Theorem 1 uses only (mu), so these are admissible too; with them a common matrix
P_0 = P_1 gives mu_0 mu_1 = 1 and removes the frequency penalty altogether.  The
product is then minimized jointly over (P_0, P_1) (a generalized-eigenvalue problem,
by bisection on mu with LMI feasibility tests).

``plain_certificate`` is the baseline: phi_0 halfway between rho(Phi_0) and 1 (in
spectral radius), phi_1 at its cheapest value, and P_p from the discrete Lyapunov
equation with identity right-hand side."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.linalg import solve_discrete_lyapunov

from ..loop.control import c2d, closed_loop, spectral_radius
from .lmi import Block, barrier_minimize, max_margin, sym_basis, vec_from_sym

if TYPE_CHECKING:
    import numpy.typing as npt

    from plants.base import Plant

    from ..loop.params import QuantizerParams
    from ..scenario import Scenario

RULES = ("paper", "tight")


# ============================================================================ the loop
@dataclass(frozen=True)
class Loop:
    """The linearized sampled-data loop the theorems are about.

    A, B : linearization of f at the origin (Section III.A); K : gain (m x n), u = K x;
    T : sampling period; M : quantization levels; Lambda = e^{L T};
    Ad = A~ = e^{A T}, Bd = B~ (exact ZOH); Phi0 = A~ + B~ K; Phi1 = A~.
    """

    A: np.ndarray
    B: np.ndarray
    K: np.ndarray
    T: float
    M: int
    Lambda: float
    Ad: np.ndarray = field(repr=False, default=None)  # type: ignore[arg-type]  # computed in __post_init__
    Bd: np.ndarray = field(repr=False, default=None)  # type: ignore[arg-type]

    def __post_init__(self):
        A = np.atleast_2d(np.asarray(self.A, dtype=float))
        B = np.asarray(self.B, dtype=float).reshape(A.shape[0], -1)
        K = np.asarray(self.K, dtype=float).reshape(B.shape[1], A.shape[0])
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "B", B)
        object.__setattr__(self, "K", K)
        Ad, Bd = c2d(A, B, self.T)
        object.__setattr__(self, "Ad", Ad)
        object.__setattr__(self, "Bd", Bd)

    @classmethod
    def from_plant(cls, plant: Plant, K: npt.ArrayLike, qp: QuantizerParams) -> Loop:
        """From a plant, a gain and QuantizerParams (T, M, Lambda = e^{L T})."""
        A, B = plant.linearization()
        return cls(A=A, B=B, K=np.asarray(K, dtype=float), T=float(qp.T), M=int(qp.M), Lambda=float(qp.Lambda))

    @classmethod
    def from_scenario(cls, sc: Scenario) -> Loop:
        return cls.from_plant(sc.make_model(), sc.K, sc.quantizer)

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def Phi0(self) -> np.ndarray:
        """A~ + B~ K (mode theta = 0)."""
        return closed_loop(self.Ad, self.Bd, self.K)

    @property
    def Phi1(self) -> np.ndarray:
        """A~ (mode theta = 1: u = 0 during DoS)."""
        return self.Ad

    @property
    def rho0(self) -> float:
        """Spectral radius of A~ + B~ K."""
        return spectral_radius(self.Phi0)

    @property
    def rho1(self) -> float:
        """Spectral radius of A~."""
        return spectral_radius(self.Phi1)

    @property
    def phi0_range(self) -> tuple[float, float]:
        """Open interval of useful phi_0: (max(rho(Phi_0)^2, Lambda^2/M^2), 1).

        phi_0 must exceed rho(Phi_0)^2 (phi_0^{-1/2} Phi_0 Schur); below Lambda^2/M^2
        it would not lower nu_0 and only shrink the feasible set of P_0, so the lower
        end is raised to Lambda^2/M^2 when that is larger (then it is attainable).
        """
        return max(self.rho0 ** 2, self.Lambda ** 2 / self.M ** 2), 1.0

    @property
    def phi1_min(self) -> float:
        """Smallest useful phi_1: max(Lambda^2, rho(A~)^2, 1), nudged up when it must be strict."""
        lo = max(self.rho1 ** 2, 1.0)
        if self.Lambda ** 2 > lo:
            return self.Lambda ** 2
        return lo * (1.0 + 1e-6)


# ============================================================================ (stability)
def stability_lhs(rho_F: npt.ArrayLike, rho_D: npt.ArrayLike, T: float, mu0: float, mu1: float, nu0: float,
                  nu1: float) -> Any:
    """Left-hand side of (stability): rho_F T ln(mu0 mu1) + (1 - rho_D*) ln nu0 + rho_D* ln nu1.

    Vectorized over rho_F and rho_D; Theorem 1 holds where it is negative.
    """
    rho_F = np.asarray(rho_F, dtype=float)
    rho_D = np.asarray(rho_D, dtype=float)
    rs = rho_D + rho_F * T
    return rho_F * T * math.log(mu0 * mu1) + (1.0 - rs) * math.log(nu0) + rs * math.log(nu1)


def lyapunov_margin(Phi: np.ndarray, P: np.ndarray, phi: float) -> float:
    """Largest eigenvalue of Phi' P Phi - phi P, relative to lambda_min(P) (< 0 when (Lyapunov) holds)."""
    S = Phi.T @ P @ Phi - phi * P
    return float(np.linalg.eigvalsh((S + S.T) / 2)[-1] / np.linalg.eigvalsh(P)[0])


def mu_pair(P0: np.ndarray, P1: np.ndarray, eta0: float, eta1: float, rule: str = "paper") -> tuple[float, float]:
    """(mu_0, mu_1) of (mu0), (mu1) (rule "paper") or the smallest constants of (mu) (rule "tight")."""
    if rule == "paper":
        a = np.linalg.eigvalsh(P1)[-1] / np.linalg.eigvalsh(P0)[0]
        b = np.linalg.eigvalsh(P0)[-1] / np.linalg.eigvalsh(P1)[0]
    elif rule == "tight":
        a, b = _gen_ratios(P0, P1)
    else:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    return max(float(a), eta1 / eta0), max(float(b), eta0 / eta1)


def _gen_ratios(P0, P1) -> tuple[float, float]:
    """(lambda_max(P0^{-1} P1), lambda_max(P1^{-1} P0)) by a Cholesky whitening of P0."""
    L = np.linalg.cholesky(P0)
    Li = np.linalg.inv(L)
    S = Li @ P1 @ Li.T
    ev = np.linalg.eigvalsh((S + S.T) / 2)
    return float(ev[-1]), float(1.0 / ev[0])


def _eta_ratio(a: float, b: float) -> float:
    """eta_1 / eta_0 in the middle (geometric) of [1/b, a], where it does not dominate mu."""
    return math.sqrt(a / b)


# ============================================================================ certificates
@dataclass(frozen=True)
class Certificate:
    """One admissible choice (phi_0, phi_1, P_0, P_1, eta_0, eta_1) and its constants.

    Normalization: lambda_min(P_0) = 1, P_1 scaled so that the two ratios of the
    rule are equal (mu_0 = mu_1), eta_1 / eta_0 at the geometric middle of its
    non-dominating range (here 1) and eta_0 = 1 unless set otherwise
    (Theorem 2 rescales).
    """

    phi0: float
    phi1: float
    P0: np.ndarray
    P1: np.ndarray
    eta0: float
    eta1: float
    T: float
    M: int
    Lambda: float
    rule: str = "paper"

    @property
    def mu(self) -> tuple[float, float]:
        return mu_pair(self.P0, self.P1, self.eta0, self.eta1, self.rule)

    @property
    def mu0(self) -> float:
        return self.mu[0]

    @property
    def mu1(self) -> float:
        return self.mu[1]

    @property
    def nu0(self) -> float:
        """(nu0): max{phi_0, Lambda^2 / M^2}."""
        return max(self.phi0, self.Lambda ** 2 / self.M ** 2)

    @property
    def nu1(self) -> float:
        """(nu1): max{phi_1, Lambda^2}."""
        return max(self.phi1, self.Lambda ** 2)

    @property
    def abc(self) -> tuple[float, float, float]:
        """(a, b, c) = (ln(mu_0 mu_1), -ln nu_0, ln nu_1)."""
        mu0, mu1 = self.mu
        return math.log(mu0 * mu1), -math.log(self.nu0), math.log(self.nu1)

    def lhs(self, rho_F: npt.ArrayLike, rho_D: npt.ArrayLike) -> Any:
        """Left-hand side of (stability) for this choice."""
        mu0, mu1 = self.mu
        return stability_lhs(rho_F, rho_D, self.T, mu0, mu1, self.nu0, self.nu1)

    def holds(self, rho_F: npt.ArrayLike, rho_D: npt.ArrayLike) -> Any:
        return self.lhs(rho_F, rho_D) < 0

    @property
    def rho_D_max(self) -> float:
        """Intercept of this choice's boundary with rho_F = 0: b / (b + c)."""
        a, b, c = self.abc
        return b / (b + c)

    @property
    def rho_F_max(self) -> float:
        """Intercept with rho_D = 0: b / (T (a + b + c))."""
        a, b, c = self.abc
        return b / (self.T * (a + b + c))

    def boundary(self, rho_D: npt.ArrayLike) -> np.ndarray:
        """rho_F on this choice's boundary line for the given rho_D (clipped at 0)."""
        a, b, c = self.abc
        return np.maximum((b - np.asarray(rho_D, dtype=float) * (b + c)) / (self.T * (a + b + c)), 0.0)

    def verify(self, Phi0: np.ndarray, Phi1: np.ndarray) -> dict:
        """Check the strict Lyapunov inequalities and positivity by eigenvalues."""
        m0 = lyapunov_margin(Phi0, self.P0, self.phi0)
        m1 = lyapunov_margin(Phi1, self.P1, self.phi1)
        pd = bool(np.linalg.eigvalsh(self.P0)[0] > 0 and np.linalg.eigvalsh(self.P1)[0] > 0)
        return {"lyapunov0": m0, "lyapunov1": m1, "ok": bool(pd and m0 < 0 and m1 < 0
                                                               and self.phi0 < 1 and self.phi1 > 1)}

    def with_eta(self, eta0: float, eta1: float) -> "Certificate":
        return replace(self, eta0=float(eta0), eta1=float(eta1))

    def scaled(self, s: float) -> "Certificate":
        """P_1 multiplied by s (P_0 and the etas unchanged)."""
        return replace(self, P1=self.P1 * float(s))

    def to_dict(self) -> dict:
        mu0, mu1 = self.mu
        return {"rule": self.rule, "phi0": self.phi0, "phi1": self.phi1, "P0": self.P0.tolist(),
                "P1": self.P1.tolist(), "eta0": self.eta0, "eta1": self.eta1, "mu0": mu0, "mu1": mu1,
                "nu0": self.nu0, "nu1": self.nu1, "rho_D_max": self.rho_D_max, "rho_F_max": self.rho_F_max}


def make_certificate(loop: Loop, phi0: float, phi1: float, P0: np.ndarray, P1: np.ndarray,
                     rule: str = "paper") -> Certificate:
    """Normalize (P_0, P_1) as described in :class:`Certificate` and wrap them."""
    P0 = _sym(np.asarray(P0, dtype=float))
    P1 = _sym(np.asarray(P1, dtype=float))
    P0 = P0 / np.linalg.eigvalsh(P0)[0]
    if rule == "paper":
        e1 = np.linalg.eigvalsh(P1)
        s = math.sqrt(np.linalg.eigvalsh(P0)[-1] / (e1[-1] * e1[0]))
    else:
        a, b = _gen_ratios(P0, P1)
        s = math.sqrt(b / a)   # P1 -> s P1 turns (a, b) into (s a, b / s): equal
    P1 = P1 * s
    cert = Certificate(phi0=float(phi0), phi1=float(phi1), P0=P0, P1=P1, eta0=1.0, eta1=1.0, T=loop.T,
                       M=loop.M, Lambda=loop.Lambda, rule=rule)
    if rule == "paper":
        a = np.linalg.eigvalsh(P1)[-1] / np.linalg.eigvalsh(P0)[0]
        b = np.linalg.eigvalsh(P0)[-1] / np.linalg.eigvalsh(P1)[0]
    else:
        a, b = _gen_ratios(P0, P1)
    return cert.with_eta(1.0, _eta_ratio(a, b))


def _sym(P):
    return (P + P.T) / 2


# ============================================================================ choices of P
def lyapunov_P(Phi: np.ndarray, phi: float) -> np.ndarray:
    """P solving (phi^{-1/2} Phi)' P (phi^{-1/2} Phi) - P = -I (the plain choice)."""
    a = Phi / math.sqrt(phi)
    P = solve_discrete_lyapunov(a.T, np.eye(Phi.shape[0]))
    return _sym(P)


def min_condition_P(Phi: np.ndarray, phi: float, *, rtol: float = 1e-7) -> tuple[np.ndarray, float]:
    """P > 0 of smallest condition number with Phi' P Phi - phi P < 0 (an LMI problem).

    Solves  min kappa  s.t.  P - I > 0,  kappa I - P > 0,  phi P - Phi' P Phi > 0
    over symmetric P and kappa by the barrier method, from the plain Lyapunov
    solution.  Returns (P, cond(P)); P satisfies the strict inequality.
    """
    n = Phi.shape[0]
    S = sym_basis(n)
    d = S.shape[0]
    I = np.eye(n)
    Z = np.zeros((1, n, n))
    blocks = [
        Block(-I, np.concatenate([S, Z])),
        Block(np.zeros((n, n)), np.concatenate([-S, I[None]])),
        Block(np.zeros((n, n)), np.concatenate([phi * S - np.einsum("ji,djk,kl->dil", Phi, S, Phi), Z])),
    ]
    P = lyapunov_P(Phi, phi)
    P = 2.0 * P / np.linalg.eigvalsh(P)[0]
    z0 = np.append(vec_from_sym(P), 2.0 * np.linalg.eigvalsh(P)[-1])
    c = np.zeros(d + 1)
    c[-1] = 1.0
    res = barrier_minimize(c, blocks, z0, rtol=rtol)
    P = _sym(np.tensordot(res.z[:d], S, axes=1))
    # the barrier optimum sits within ~1e-9 of the boundary; blend in 1e-6 of the
    # Lyapunov solution (strictly inside) so the strict inequality has visible room
    PL = lyapunov_P(Phi, phi)
    P = P + 1e-6 * (np.linalg.eigvalsh(P)[0] / np.linalg.eigvalsh(PL)[0]) * PL
    ev = np.linalg.eigvalsh(P)
    return P, float(ev[-1] / ev[0])


def _trace_free_basis(n: int) -> np.ndarray:
    """Basis of the symmetric trace-zero n x n matrices (dimension n (n + 1) / 2 - 1)."""
    out = []
    for i in range(n):
        for j in range(i, n):
            if i == j:
                if i == n - 1:
                    continue
                E = np.zeros((n, n))
                E[i, i] = 1.0
                E[n - 1, n - 1] = -1.0
            else:
                E = np.zeros((n, n))
                E[i, j] = E[j, i] = 1.0
            out.append(E)
    return np.array(out).reshape(-1, n, n)


def _lyap_op(Phi, phi, S):
    """phi S_i - Phi' S_i Phi for every basis matrix S_i."""
    return phi * S - np.einsum("ji,djk,kl->dil", Phi, S, Phi)


def common_P(Phi0: np.ndarray, phi0: float, Phi1: np.ndarray, phi1: float, *,
             start: np.ndarray | None = None) -> np.ndarray | None:
    """A common P > 0 with Phi_p' P Phi_p - phi_p P < 0 for p = 0, 1, or None.

    Phase-I LMI problem with tr P = 1: maximize t s.t. P, phi_p P - Phi_p' P Phi_p >= t I.
    """
    n = Phi0.shape[0]
    F = _trace_free_basis(n)
    P_c = np.eye(n) / n
    blocks = [Block(P_c, F),
              Block(_lyap_op(Phi0, phi0, P_c[None])[0], _lyap_op(Phi0, phi0, F)),
              Block(_lyap_op(Phi1, phi1, P_c[None])[0], _lyap_op(Phi1, phi1, F))]
    P = lyapunov_P(Phi0, phi0) if start is None else start
    P = P / np.trace(P)
    x0 = np.array([np.sum((P - P_c) * Fi) / np.sum(Fi * Fi) for Fi in F]) if len(F) else np.zeros(0)
    x, t = max_margin(blocks, x0, stop_at=1e-9)
    if t <= 1e-9:
        return None
    P = _sym(P_c + np.tensordot(x, F, axes=1))
    if lyapunov_margin(Phi0, P, phi0) < 0 and lyapunov_margin(Phi1, P, phi1) < 0:
        return P
    return None


def min_relative_condition(Phi0: np.ndarray, phi0: float, Phi1: np.ndarray, phi1: float, *, P0_start: np.ndarray,
                           P1_start: np.ndarray, tol: float = 5e-3,
                           max_iter: int = 40, lower: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """(P_0, P_1) minimizing lambda_max(P_0^{-1} P_1) lambda_max(P_1^{-1} P_0) (rule "tight").

    With the scaling P_0 <= P_1 the product is mu with P_1 <= mu P_0; bisection on
    ln mu with the phase-I test of  P_0 >= t I, phi_p P_p - Phi_p' P_p Phi_p >= t I,
    P_1 - P_0 >= t I, mu P_0 - P_1 >= t I  (tr P_0 = 1).  The start pair must be
    admissible; its product is the upper end of the bisection, ``lower`` (a known
    lower bound of the minimum, default 1) the lower end; ``tol`` is the bracket
    width in ln mu.  Returns (P0, P1, mu).
    """
    n = Phi0.shape[0]
    F = _trace_free_basis(n)
    S = sym_basis(n)
    d0, d1 = F.shape[0], S.shape[0]
    P_c = np.eye(n) / n
    Z0 = np.zeros((d0, n, n))
    Z1 = np.zeros((d1, n, n))

    def blocks(mu):
        return [
            Block(P_c, np.concatenate([F, Z1])),
            Block(_lyap_op(Phi0, phi0, P_c[None])[0], np.concatenate([_lyap_op(Phi0, phi0, F), Z1])),
            Block(np.zeros((n, n)), np.concatenate([Z0, _lyap_op(Phi1, phi1, S)])),
            Block(-P_c, np.concatenate([-F, S])),
            Block(mu * P_c, np.concatenate([mu * F, -S])),
        ]

    P0 = P0_start / np.trace(P0_start)
    a, b = _gen_ratios(P0, P1_start)
    P1 = P1_start * b                   # now lambda_max(P1^{-1} P0) = 1: P0 <= P1, tightly
    best = (P0, P1, a * b)
    lo, hi = math.log(max(lower, 1.0)), math.log(a * b)
    x_start = np.concatenate([[np.sum((P0 - P_c) * Fi) / np.sum(Fi * Fi) for Fi in F], vec_from_sym(P1)])
    for _ in range(max_iter):
        if hi - lo < tol:
            break
        mid = 0.5 * (lo + hi)
        try:
            x, t = max_margin(blocks(math.exp(mid)), x_start, stop_at=1e-10)
        except (np.linalg.LinAlgError, ValueError):
            t = -1.0
        if t > 1e-10:
            Q0 = _sym(P_c + np.tensordot(x[:d0], F, axes=1))
            Q1 = _sym(np.tensordot(x[d0:], S, axes=1))
            ok = lyapunov_margin(Phi0, Q0, phi0) < 0 and lyapunov_margin(Phi1, Q1, phi1) < 0
            if ok:
                a2, b2 = _gen_ratios(Q0, Q1)
                if a2 * b2 < best[2]:
                    best = (Q0, Q1, a2 * b2)
                hi = min(mid, math.log(a2 * b2))
                x_start = x
                continue
        lo = mid
    return best


def plain_certificate(loop: Loop) -> Certificate:
    """The baseline choice: phi_0 = ((rho(Phi_0) + 1) / 2)^2 (at least Lambda^2/M^2),
    phi_1 = its cheapest value, P_p from the Lyapunov equation with identity (rule "paper")."""
    phi0 = max(((loop.rho0 + 1.0) / 2.0) ** 2, loop.Lambda ** 2 / loop.M ** 2)
    phi1 = loop.phi1_min
    return make_certificate(loop, phi0, phi1, lyapunov_P(loop.Phi0, phi0), lyapunov_P(loop.Phi1, phi1))
