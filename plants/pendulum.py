"""Inverted pendulum about its upright equilibrium.

    x1 = angle from upright [rad], x2 = angular velocity
    x1' = x2
    x2' = (g / l) sin x1 - c / (mass l^2) x2 + u / (mass l^2)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .base import Plant, rhs_function


@rhs_function
def pendulum_rhs(x: np.ndarray, u: np.ndarray, p: np.ndarray, dx: np.ndarray) -> None:
    g, l, mass, c = p[0], p[1], p[2], p[3]
    ml2 = mass * l * l
    dx[0] = x[1]
    dx[1] = (g / l) * math.sin(x[0]) - (c / ml2) * x[1] + u[0] / ml2


@dataclass(frozen=True)
class Pendulum(Plant):
    g: float = 9.81
    l: float = 1.0
    mass: float = 1.0
    damping: float = 0.1

    name: ClassVar[str] = "pendulum"
    rhs: ClassVar = pendulum_rhs
    description: ClassVar[str] = "inverted pendulum, upright equilibrium (n = 2, m = 1)"
    lipschitz_region: ClassVar[float] = math.pi

    def __post_init__(self) -> None:
        for k in ("l", "mass"):
            if not getattr(self, k) > 0:
                raise ValueError(f"pendulum: {k} must be > 0, got {getattr(self, k)}")

    @property
    def n(self) -> int:
        return 2

    @property
    def m(self) -> int:
        return 1

    def param_vector(self) -> np.ndarray:
        return np.array([self.g, self.l, self.mass, self.damping], dtype=np.float64)

    def linearization(self) -> tuple[np.ndarray, np.ndarray]:
        ml2 = self.mass * self.l**2
        A = np.array([[0.0, 1.0], [self.g / self.l, -self.damping / ml2]])
        B = np.array([[0.0], [1.0 / ml2]])
        return A, B

    def input_gain(self, varrho: float, u_bound: float = 10.0, grid: int = 21, h: float = 1e-6) -> float:
        """L_u = 1 / (mass l^2) exactly (u enters x2' only, linearly)."""
        return 1.0 / (self.mass * self.l ** 2)

    def remainder_gain(self, r: float, u_bound: float | None = None, grid: int | None = None) -> float:
        """Exact gain of the remainder g(x, u) = (0, (g/l)(sin x1 - x1)) on ||x||_inf <= r.

        ||g||_inf / (||x||_inf + ||u||_inf) <= (g/l) |1 - sin(x1)/x1| with equality at
        |x1| = ||x||_inf, u = 0.  sin(s)/s decreases on [0, s*] (s* = 4.4934, where
        tan s = s, the global minimum -0.2172), so G(r) = (g/l)(1 - sinc(min(r, s*))).
        See :meth:`Plant.remainder_gain`.
        """
        s = min(float(r), 4.493409457909064)
        if s <= 0.0:
            return 0.0
        return abs(self.g / self.l) * (1.0 - math.sin(s) / s)
