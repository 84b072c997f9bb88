"""Cart-pole (n = 4, m = 1) about the upright equilibrium, frictionless.

State x = [p, v, theta, omega]: cart position and velocity, pole angle from
upright and its rate; u is the horizontal force on the cart.  With
M_t = m_c + m_p and l the half length of the pole:

    theta'' = (g sin th - cos th (u + m_p l w^2 sin th) / M_t) / (l (4/3 - m_p cos^2 th / M_t))
    p''     = (u + m_p l (w^2 sin th - theta'' cos th)) / M_t
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .base import Plant, rhs_function


@rhs_function
def cartpole_rhs(x: np.ndarray, u: np.ndarray, p: np.ndarray, dx: np.ndarray) -> None:
    m_c, m_p, l, g = p[0], p[1], p[2], p[3]
    Mt = m_c + m_p
    th = x[2]
    w = x[3]
    s = math.sin(th)
    c = math.cos(th)
    tmp = (u[0] + m_p * l * w * w * s) / Mt
    thdd = (g * s - c * tmp) / (l * (4.0 / 3.0 - m_p * c * c / Mt))
    dx[0] = x[1]
    dx[1] = tmp - m_p * l * thdd * c / Mt
    dx[2] = w
    dx[3] = thdd


@dataclass(frozen=True)
class CartPole(Plant):
    m_c: float = 1.0
    m_p: float = 0.1
    l: float = 0.5
    g: float = 9.81

    name: ClassVar[str] = "cartpole"
    rhs: ClassVar = cartpole_rhs
    description: ClassVar[str] = "cart-pole, upright equilibrium (n = 4, m = 1)"
    lipschitz_region: ClassVar[float] = 1.0

    def __post_init__(self) -> None:
        for k in ("m_c", "m_p", "l"):
            if not getattr(self, k) > 0:
                raise ValueError(f"cartpole: {k} must be > 0, got {getattr(self, k)}")

    @property
    def n(self) -> int:
        return 4

    @property
    def m(self) -> int:
        return 1

    def param_vector(self) -> np.ndarray:
        return np.array([self.m_c, self.m_p, self.l, self.g], dtype=np.float64)

    def linearization(self) -> tuple[np.ndarray, np.ndarray]:
        Mt = self.m_c + self.m_p
        den = self.l * (4.0 / 3.0 - self.m_p / Mt)
        a_t = self.g / den            # d theta'' / d theta
        b_t = -1.0 / (Mt * den)       # d theta'' / d u
        A = np.zeros((4, 4))
        A[0, 1] = 1.0
        A[2, 3] = 1.0
        A[3, 2] = a_t
        A[1, 2] = -self.m_p * self.l * a_t / Mt
        B = np.zeros((4, 1))
        B[3, 0] = b_t
        B[1, 0] = (1.0 - self.m_p * self.l * b_t) / Mt
        return A, B
