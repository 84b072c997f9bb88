"""Theorem 1's allowable region of (rho_F, rho_D): the union over the certificates
(``testbed.analysis.theorem1``) of the triangles where (stability) holds, maximized over the grids of
phi_0 and phi_1; and the summary of Theorem 1 for a scenario."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .regioncache import paper_solves
from .theorem1 import (
    RULES,
    Certificate,
    Loop,
    _gen_ratios,
    common_P,
    lyapunov_margin,
    make_certificate,
    min_condition_P,
    min_relative_condition,
    plain_certificate,
)

if TYPE_CHECKING:
    import numpy.typing as npt


# ============================================================================ the region
@dataclass
class Region:
    """The allowable region of Theorem 1 as the union over a family of certificates.

    ``a, b, c`` are (n_phi0, n_phi1) arrays of ln(mu_0 mu_1), -ln nu_0, ln nu_1 over
    the (phi_0, phi_1) grid (each entry backed by ``certificate(i, j)``);
    ``rho_D`` / ``rho_F`` sample the upper envelope (the boundary).
    """

    loop: Loop
    rule: str
    phi0: np.ndarray
    phi1: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    P0: list
    P1: list
    rho_D: np.ndarray = None  # type: ignore[assignment]  # None: 201 points up to rho_D_max (__post_init__)
    rho_F: np.ndarray = None  # type: ignore[assignment]  # computed in __post_init__
    arg: np.ndarray = None   # type: ignore[assignment]  # flat (i, j) index achieving each boundary point

    def __post_init__(self) -> None:
        if self.rho_D is None:
            self.rho_D = np.linspace(0.0, self.rho_D_max, 201)
        self.rho_F, self.arg = self.envelope(self.rho_D)

    # --- envelope
    def envelope(self, rho_D: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Boundary rho_F^max(rho_D) (0 where no rho_F is allowed) and the certificate index."""
        rho_D = np.atleast_1d(np.asarray(rho_D, dtype=float))
        a, b, c = self.a.ravel(), self.b.ravel(), self.c.ravel()
        val = (b[None, :] - rho_D[:, None] * (b + c)[None, :]) / (self.loop.T * (a + b + c))[None, :]
        val = np.where(np.isfinite(val), val, -np.inf)
        k = np.argmax(val, axis=1)
        return np.maximum(val[np.arange(len(rho_D)), k], 0.0), k

    def lhs_min(self, rho_F: npt.ArrayLike, rho_D: npt.ArrayLike) -> np.ndarray:
        """min over the certificates of the left-hand side of (stability) (< 0: Theorem 1 holds)."""
        rho_F = np.asarray(rho_F, dtype=float)
        rho_D = np.asarray(rho_D, dtype=float)
        rs = (rho_D + rho_F * self.loop.T)[..., None]
        a, b, c = self.a.ravel(), self.b.ravel(), self.c.ravel()
        v = rho_F[..., None] * self.loop.T * a - (1.0 - rs) * b + rs * c
        return np.min(np.where(np.isfinite(v), v, np.inf), axis=-1)

    def holds(self, rho_F: npt.ArrayLike, rho_D: npt.ArrayLike) -> Any:
        """Theorem 1's condition holds for (rho_F, rho_D) with some certificate of the family."""
        return self.lhs_min(rho_F, rho_D) < 0

    @property
    def rho_D_max(self) -> float:
        """Boundary at rho_F = 0: max over the family of b / (b + c)."""
        return float(np.nanmax(self.b / (self.b + self.c)))

    @property
    def rho_F_max(self) -> float:
        """Boundary at rho_D = 0: max over the family of b / (T (a + b + c))."""
        return float(np.nanmax(self.b / (self.loop.T * (self.a + self.b + self.c))))

    @property
    def area(self) -> float:
        """Area under the boundary in the (rho_D, rho_F) plane (trapezoid rule on the rho_D grid)."""
        return float(np.trapezoid(self.rho_F, self.rho_D))

    # --- certificates
    def certificate(self, i: int, j: int) -> Certificate:
        return make_certificate(self.loop, self.phi0[i], self.phi1[j], self.P0[i][j] if self.rule == "tight"
                                else self.P0[i], self.P1[i][j] if self.rule == "tight" else self.P1[j],
                                rule=self.rule)

    def _ij(self, flat: int) -> tuple[int, int]:
        i, j = np.unravel_index(flat, self.a.shape)
        return int(i), int(j)

    def best_for(self, rho_F: float, rho_D: float) -> Certificate:
        """The certificate with the most negative (stability) left-hand side at (rho_F, rho_D)."""
        rs = rho_D + rho_F * self.loop.T
        v = rho_F * self.loop.T * self.a - (1.0 - rs) * self.b + rs * self.c
        v = np.where(np.isfinite(v), v, np.inf)
        return self.certificate(*self._ij(int(np.argmin(v))))

    def best_area(self) -> Certificate:
        """The single certificate whose own triangle has the largest area."""
        tri = self.b / (self.b + self.c) * self.b / (self.loop.T * (self.a + self.b + self.c))
        tri = np.where(np.isfinite(tri), tri, -np.inf)
        return self.certificate(*self._ij(int(np.argmax(tri))))

    def argmax_rho_F(self) -> Certificate:
        v = self.b / (self.loop.T * (self.a + self.b + self.c))
        return self.certificate(*self._ij(int(np.nanargmax(v))))

    def to_dict(self, n_points: int = 41) -> dict:
        idx = np.unique(np.linspace(0, len(self.rho_D) - 1, n_points).round().astype(int))
        return {"rule": self.rule, "rho_D_max": self.rho_D_max, "rho_F_max": self.rho_F_max, "area": self.area,
                "boundary": {"rho_D": self.rho_D[idx].tolist(), "rho_F": self.rho_F[idx].tolist()}}


def phi0_grid(loop: Loop, n: int = 48) -> np.ndarray:
    """phi_0 values in (lo, 1), dense near the lower end lo = max(rho(Phi_0)^2, Lambda^2/M^2).

    The lowest is lo + 1e-4 (1 - lo) (lo itself when it is Lambda^2/M^2): closer to
    rho(Phi_0)^2 the Lyapunov inequality of the optimal P_0 has almost no room left.
    """
    lo, hi = loop.phi0_range
    attainable = loop.Lambda ** 2 / loop.M ** 2 >= loop.rho0 ** 2
    u = np.geomspace(1e-4, 0.98, n)
    g = lo + (hi - lo) * u
    if attainable:
        g = np.concatenate([[lo], g])
    return g


def phi1_grid(loop: Loop, n: int = 8) -> np.ndarray:
    """phi_1 values from the cheapest one, phi1_min, to 20 phi1_min (geometric)."""
    return loop.phi1_min * np.geomspace(1.0, 20.0, n)


def allowable_region(loop: Loop, rule: str = "paper", *, n_phi0: int | None = None, n_phi1: int | None = None,
                     rho_D: np.ndarray | None = None) -> Region:
    """The (certified) allowable region of Theorem 1 optimized over (phi, P, eta).

    rule "paper": mu from (mu0), (mu1); ln(mu_0 mu_1) = ln cond(P_0) + ln cond(P_1),
    each minimized by :func:`min_condition_P`.  rule "tight": smallest constants of
    (mu), minimized jointly (common P first, else :func:`min_relative_condition`).
    Grid sizes default to 48 x 8 (paper) and 24 x 4 (tight: a bisection per point
    where no common P exists).
    """
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    n_phi0 = n_phi0 or (48 if rule == "paper" else 24)
    n_phi1 = n_phi1 or (8 if rule == "paper" else 4)
    g0 = phi0_grid(loop, n_phi0)
    g1 = phi1_grid(loop, n_phi1)
    grid = {} if rho_D is None else {"rho_D": rho_D}  # none given: Region's own grid up to rho_D_max
    Lam2M2 = loop.Lambda ** 2 / loop.M ** 2
    b = -np.log(np.maximum(g0, Lam2M2))[:, None] * np.ones((1, len(g1)))
    c = np.ones((len(g0), 1)) * np.log(np.maximum(g1, loop.Lambda ** 2))[None, :]
    if rule == "paper":  # the same solves for the same matrices and grids: kept on disk (``regioncache``)
        P0s, k0, P1s, k1 = paper_solves(loop.Phi0, g0, loop.Phi1, g1, min_condition_P)
        a = np.log(np.array(k0))[:, None] + np.log(np.array(k1))[None, :]
        return Region(loop, rule, g0, g1, a, b, c, list(P0s), list(P1s), **grid)
    # tight: a(phi_0, phi_1) = min ln(mu_0 mu_1) is nonincreasing in both phis (larger
    # phi, larger feasible sets), so a pair found at (i, j - 1) is admissible at (i, j)
    # (upper bound) and a(i + 1, j) is a lower bound: rows are done from large phi_0 down
    P0s = [[None] * len(g1) for _ in g0]
    P1s = [[None] * len(g1) for _ in g0]
    a = np.full((len(g0), len(g1)), np.inf)
    paper0 = {}
    for j, p1 in enumerate(g1):
        for i in reversed(range(len(g0))):
            p0 = g0[i]
            cands = []
            if j > 0:
                cands.append((P0s[i][j - 1], P1s[i][j - 1]))
            if i + 1 < len(g0) and a[i + 1, j] == 0.0:
                cands.append((P0s[i + 1][j], P1s[i + 1][j]))
            P = next((Q0 for Q0, Q1 in cands if Q0 is Q1 and lyapunov_margin(loop.Phi0, Q0, p0) < 0
                      and lyapunov_margin(loop.Phi1, Q0, p1) < 0), None)
            if P is None:
                if i not in paper0:
                    paper0[i] = min_condition_P(loop.Phi0, p0)[0]
                P = common_P(loop.Phi0, p0, loop.Phi1, p1, start=paper0[i])
            if P is not None:
                P0s[i][j] = P1s[i][j] = P
                a[i, j] = 0.0
                continue
            lo = math.exp(a[i + 1, j]) if i + 1 < len(g0) else 1.0
            if j > 0:
                S0, S1 = P0s[i][j - 1], P1s[i][j - 1]
            else:
                S0, S1 = paper0[i], min_condition_P(loop.Phi1, p1)[0]
            ra, rb = _gen_ratios(S0, S1)
            if math.log(ra * rb) - math.log(lo) < 5e-3:
                Q0, Q1, mu = S0, S1, ra * rb
            else:
                Q0, Q1, mu = min_relative_condition(loop.Phi0, p0, loop.Phi1, p1, P0_start=S0, P1_start=S1,
                                                    lower=lo)
            P0s[i][j], P1s[i][j] = Q0, Q1
            a[i, j] = math.log(mu)
    return Region(loop, rule, g0, g1, a, b, c, P0s, P1s, **grid)


# ============================================================================ summary
def analyze_theorem1(loop: Loop, budget: Sequence[float] | None = None, *, rules: Iterable[str] = RULES,
                     n_phi0: int | None = None,
                     n_phi1: int | None = None, rule: str = "paper") -> dict:
    """Theorem 1 for a loop: plain choice, optimized regions per rule, verdict for a budget.

    ``budget`` is (kappa_F, rho_F, kappa_D, rho_D) or None.  The headline
    constants (phi0, phi1, mu0, mu1, nu0, nu1, ...) are those of the ``rule``
    certificate with the most negative (stability) left-hand side at the budget's
    (rho_F, rho_D), or, without a budget, of the certificate whose own triangle is
    largest.  rho_D_max / rho_F_max are the envelope's intercepts.  Grid sizes:
    see :func:`allowable_region`.
    """
    out: dict = {"n": loop.n, "T": loop.T, "M": loop.M, "Lambda": loop.Lambda, "K": loop.K.tolist(),
                 "rho_Phi0": loop.rho0, "rho_Phi1": loop.rho1,
                 "phi0_range": list(loop.phi0_range), "phi1_min": loop.phi1_min}
    plain = plain_certificate(loop)
    out["plain"] = plain.to_dict()
    regions = {}
    for r in rules:
        regions[r] = allowable_region(loop, r, n_phi0=n_phi0, n_phi1=n_phi1)
        out[r] = regions[r].to_dict()
    reg = regions.get(rule) or next(iter(regions.values()))
    if budget is not None:
        _, rF, _, rD = budget
        cert = reg.best_for(rF, rD)
        out["choice"] = "largest margin of (stability) at the budget's (rho_F, rho_D)"
    else:
        cert = reg.best_area()
        out["choice"] = "certificate with the largest own triangle"
    out["certificate"] = cert.to_dict()
    out["certificate"]["verify"] = cert.verify(loop.Phi0, loop.Phi1)
    out["rule"] = reg.rule
    out["rho_D_max"] = reg.rho_D_max
    out["rho_F_max"] = reg.rho_F_max
    if budget is not None:
        _, rF, _, rD = budget
        out["theorem1_holds"] = bool(reg.holds(rF, rD))
        out["stability_lhs"] = float(reg.lhs_min(rF, rD))
        for name, region in regions.items():
            out[name]["theorem1_holds"] = bool(region.holds(rF, rD))
        out["plain"]["theorem1_holds"] = bool(plain.holds(rF, rD))
    out["_regions"] = regions
    out["_certificate"] = cert
    out["_plain"] = plain
    return out
