"""The Lienard system of the paper's Section V.

    z'' - (1 - 3 a z^2 - 5 b z^4) z' + z = u

in the coordinates x1 = z, x2 = z' - int_0^z (1 + 3 a w^2 - 5 b w^4) dw:

    x1' = x2 + x1 + a x1^3 - b x1^5
    x2' = -x1 + u

with a = 1/3, b = 1/50.  The origin is unstable; the uncontrolled system has a
stable limit cycle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .base import Plant, rhs_function


@rhs_function
def lienard_rhs(x: np.ndarray, u: np.ndarray, p: np.ndarray, dx: np.ndarray) -> None:
    x1 = x[0]
    x1sq = x1 * x1
    dx[0] = x[1] + x1 + p[0] * x1 * x1sq - p[1] * x1 * x1sq * x1sq
    dx[1] = -x1 + u[0]


@dataclass(frozen=True)
class Lienard(Plant):
    a: float = 1.0 / 3.0
    b: float = 1.0 / 50.0

    name: ClassVar[str] = "lienard"
    rhs: ClassVar = lienard_rhs
    description: ClassVar[str] = "Lienard oscillator of the paper (n = 2, m = 1)"
    #: the paper states L = 10 holds on a region D larger than the nominal region of attraction;
    #: sup ||df/dx||_inf = 1 + |1 + 3a x1^2 - 5b x1^4| <= 10 holds for |x1| <= 4.02.
    lipschitz_region: ClassVar[float] = 4.0

    @property
    def n(self) -> int:
        return 2

    @property
    def m(self) -> int:
        return 1

    def param_vector(self) -> np.ndarray:
        return np.array([self.a, self.b], dtype=np.float64)

    def linearization(self) -> tuple[np.ndarray, np.ndarray]:
        A = np.array([[1.0, 1.0], [-1.0, 0.0]])
        B = np.array([[0.0], [1.0]])
        return A, B

    def input_gain(self, varrho: float, u_bound: float = 10.0, grid: int = 21, h: float = 1e-6) -> float:
        """L_u = ||B||_inf = 1 exactly (u enters x2' = -x1 + u only)."""
        return 1.0

    def remainder_gain(self, r: float, u_bound: float | None = None, grid: int | None = None) -> float:
        """Exact gain of the remainder g(x, u) = (a x1^3 - b x1^5, 0) on ||x||_inf <= r.

        ||g||_inf / (||x||_inf + ||u||_inf) <= |a x1^2 - b x1^4| (take |x1| = ||x||_inf,
        u = 0 for equality), so G(r) = max over s in [0, r^2] of |a s - b s^2|: the end
        point s = r^2 or the vertex s = a / (2 b).  The input does not enter g, so
        u_bound and grid are ignored.  See :meth:`Plant.remainder_gain`.
        """
        s_max = float(r) ** 2
        cands = [s_max]
        if self.b != 0.0 and 0.0 < self.a / (2.0 * self.b) < s_max:
            cands.append(self.a / (2.0 * self.b))
        return max(abs(self.a * s - self.b * s * s) for s in cands)
