"""A linear plant x' = A x + B u (the remainder g of the linearization is zero).

Useful to check the analysis on a case with a known answer.  Parameters are the
matrices themselves: ``params = { A = [[...]], B = [[...]] }``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from .base import Plant, rhs_function

if TYPE_CHECKING:
    import numpy.typing as npt


@rhs_function
def linear_rhs(x: np.ndarray, u: np.ndarray, p: np.ndarray, dx: np.ndarray) -> None:
    n = int(p[0])
    m = int(p[1])
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += p[2 + i * n + j] * x[j]
        for j in range(m):
            acc += p[2 + n * n + i * m + j] * u[j]
        dx[i] = acc


def _as_tuple2(a: Iterable[Iterable[float]]) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in a)


@dataclass(frozen=True)
class Linear(Plant):
    A_: tuple = field(default=((0.0, 1.0), (2.0, -1.0)))
    B_: tuple = field(default=((0.0,), (1.0,)))

    name: ClassVar[str] = "linear"
    rhs: ClassVar = linear_rhs
    description: ClassVar[str] = "linear plant x' = A x + B u (any n, m)"
    lipschitz_region: ClassVar[float] = float("inf")

    def __post_init__(self) -> None:
        A = np.asarray(self.A_, dtype=float)
        B = np.asarray(self.B_, dtype=float)
        if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
            raise ValueError(f"linear: A must be a square n x n matrix, got shape {A.shape}")
        if B.ndim != 2 or B.shape[0] != A.shape[0] or B.shape[1] == 0:
            raise ValueError(f"linear: B must be n x m with n = {A.shape[0]}, got shape {B.shape}")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
            raise ValueError("linear: A and B must be finite")
        object.__setattr__(self, "A_", _as_tuple2(A))
        object.__setattr__(self, "B_", _as_tuple2(B))

    @classmethod
    def from_params(cls, A: npt.ArrayLike | None = None, B: npt.ArrayLike | None = None) -> Linear:
        kw: dict[str, Any] = {}
        if A is not None:
            kw["A_"] = A
        if B is not None:
            kw["B_"] = B
        return cls(**kw)

    def params_dict(self) -> dict[str, Any]:
        return {"A": [list(r) for r in self.A_], "B": [list(r) for r in self.B_]}

    @property
    def n(self) -> int:
        return len(self.A_)

    @property
    def m(self) -> int:
        return len(self.B_[0])

    def param_vector(self) -> np.ndarray:
        A = np.asarray(self.A_, dtype=float)
        B = np.asarray(self.B_, dtype=float)
        return np.concatenate([[A.shape[0], B.shape[1]], A.ravel(), B.ravel()])

    def linearization(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.A_, dtype=float), np.asarray(self.B_, dtype=float)

    def remainder_gain(self, r: float, u_bound: float | None = None, grid: int | None = None) -> float:
        """The remainder g of a linear plant is identically zero (see :meth:`Plant.remainder_gain`)."""
        return 0.0
