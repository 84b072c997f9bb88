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

import numba as nb
import numpy as np

from .base import Plant


@nb.njit(cache=True)
def lienard_rhs(x, u, p, dx):
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

    def linearization(self):
        A = np.array([[1.0, 1.0], [-1.0, 0.0]])
        B = np.array([[0.0], [1.0]])
        return A, B
