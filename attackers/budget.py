"""Exact checker for the averagely constrained DoS class (paper, Section II.C).

* Assumption 3 (DoS frequency): ``N(t) <= kappa_F + rho_F t`` for all ``t >= 0``.
* Assumption 4 (DoS duration):  ``|A(t)| <= kappa_D + rho_D t`` for all ``t >= 0``,
  ``rho_D in [0, 1)``.

Both ``N(t) - rho_F t`` and ``|A(t)| - rho_D t`` are piecewise linear with
breakpoints at the attack starts ``a_i`` and ends ``a_i + tau_i`` (plus ``0`` and
the horizon), so their suprema are evaluated exactly on these event times:
``N(t) - rho_F t`` peaks at attack starts (``N`` is right-continuous), and
``|A(t)| - rho_D t`` peaks at ends of merged intervals (slope ``1 - rho_D > 0``
inside an attack, ``-rho_D`` outside).  No time grid is used.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .checks import RHO_D_WHY, field
from .schedule import Schedule

__all__ = ["BudgetReport", "RealizedRates", "check", "satisfies", "realized_rates"]


def _coerce_schedule(schedule: Schedule | Iterable[Iterable[float]]) -> Schedule:
    if isinstance(schedule, Schedule):
        return schedule
    return Schedule(tuple(tuple(p) for p in schedule))  # type: ignore[misc]  # __post_init__ checks the pairs


def _check_nonneg(name: str, value: object, *, upper_open: float | None = None) -> float:
    if upper_open is not None:
        return field(name, value, RHO_D_WHY, lo=0.0, hi=upper_open, hi_open=True)
    return field(name, value, lo=0.0)


def _check_horizon(horizon: object) -> float | None:
    if horizon is None:
        return None
    h = _check_nonneg("horizon", horizon)
    return h


@dataclass(frozen=True)
class BudgetReport:
    """Result of :func:`check`.

    Attributes
    ----------
    rho_F, rho_D, horizon:
        The rates the report was computed for and the horizon (``None`` = all ``t >= 0``).
    kappa_F_min:
        ``max(0, sup_{t in [0, horizon]} N(t) - rho_F t)``: the smallest
        ``kappa_F >= 0`` for which Assumption 3 holds with ``rho_F``.
    kappa_D_min:
        ``max(0, sup_{t in [0, horizon]} |A(t)| - rho_D t)``: the smallest
        ``kappa_D >= 0`` for which Assumption 4 holds with ``rho_D``.
    t_kappa_F, t_kappa_D:
        A time where the respective supremum is attained (``0.0`` if it is 0).
    t_events:
        Sorted event times (``0``, every start and end, the horizon), clipped
        to ``[0, horizon]``; all breakpoints of ``N`` and ``|A|``.
    N, A:
        ``N(t)`` and ``|A(t)|`` at ``t_events``.
    n_attacks, total_duration:
        ``N(horizon)`` and ``|A(horizon)|`` (all attacks / their union's measure
        if ``horizon`` is ``None``).
    """

    rho_F: float
    rho_D: float
    horizon: float | None
    kappa_F_min: float
    kappa_D_min: float
    t_kappa_F: float
    t_kappa_D: float
    t_events: np.ndarray
    N: np.ndarray
    A: np.ndarray
    n_attacks: int
    total_duration: float

    def satisfies(self, kappa_F: float, kappa_D: float, tol: float = 1e-9) -> bool:
        """Whether Assumptions 3 and 4 hold with ``kappa_F``, ``kappa_D`` (see :func:`satisfies`)."""
        kappa_F = _check_nonneg("kappa_F", kappa_F)
        kappa_D = _check_nonneg("kappa_D", kappa_D)
        t = self.t_events
        rhs_F = kappa_F + self.rho_F * t
        rhs_D = kappa_D + self.rho_D * t
        ok_F = np.all(self.N <= rhs_F + tol * np.maximum(1.0, rhs_F))
        ok_D = np.all(self.A <= rhs_D + tol * np.maximum(1.0, rhs_D))
        return bool(ok_F and ok_D)


def check(schedule: Schedule | Iterable[Iterable[float]], rho_F: float, rho_D: float,
          horizon: float | None = None) -> BudgetReport:
    """Smallest ``kappa_F``, ``kappa_D`` making Assumptions 3 and 4 hold.

    Parameters
    ----------
    schedule:
        A :class:`~attackers.schedule.Schedule` (or a sequence of ``(a_i, tau_i)``).
    rho_F:
        Average attack frequency ``rho_F >= 0`` (Assumption 3).
    rho_D:
        Average attack duration ratio ``rho_D in [0, 1)`` (Assumption 4).
    horizon:
        Check ``t in [0, horizon]`` only; ``None`` checks all ``t >= 0``.

    Exact: merges the intervals for ``|A(t)|`` and evaluates both
    ``N(t) - rho_F t`` and ``|A(t)| - rho_D t`` at all their breakpoints.
    """
    sch = _coerce_schedule(schedule)
    rho_F = _check_nonneg("rho_F", rho_F)
    rho_D = _check_nonneg("rho_D", rho_D, upper_open=1.0)
    H = _check_horizon(horizon)

    ev = np.concatenate(([0.0], sch.starts, sch.ends))
    if H is not None:
        ev = np.concatenate((ev[ev <= H], [H]))
    t = np.unique(ev)
    N = sch.count(t)
    A = sch.union_length(t)

    gF = N - rho_F * t
    gD = A - rho_D * t
    iF = int(np.argmax(gF))
    iD = int(np.argmax(gD))
    kF = max(0.0, float(gF[iF]))
    kD = max(0.0, float(gD[iD]))

    if H is None:
        n_attacks = len(sch)
        total = sch.total_duration
    else:
        n_attacks = int(sch.count(H))
        total = float(sch.union_length(H))

    return BudgetReport(
        rho_F=rho_F,
        rho_D=rho_D,
        horizon=H,
        kappa_F_min=kF,
        kappa_D_min=kD,
        t_kappa_F=float(t[iF]) if kF > 0.0 else 0.0,
        t_kappa_D=float(t[iD]) if kD > 0.0 else 0.0,
        t_events=t,
        N=N,
        A=A,
        n_attacks=n_attacks,
        total_duration=total,
    )


def satisfies(
    schedule: Schedule | Iterable[Iterable[float]],
    kappa_F: float,
    rho_F: float,
    kappa_D: float,
    rho_D: float,
    horizon: float | None = None,
    tol: float = 1e-9,
) -> bool:
    """Whether ``schedule`` satisfies Assumption 3 ``(kappa_F, rho_F)`` and Assumption 4 ``(kappa_D, rho_D)``.

    Checked exactly at every event time ``t`` in ``[0, horizon]``, with a
    floating-point allowance: ``N(t) <= kappa_F + rho_F t + tol * max(1, kappa_F + rho_F t)``
    and likewise for ``|A(t)|`` (``tol`` is relative to the bound, absolute below 1).
    """
    return check(schedule, rho_F, rho_D, horizon).satisfies(kappa_F, kappa_D, tol=tol)


class RealizedRates(NamedTuple):
    """Empirical rates over ``[0, horizon]``: ``N(horizon)/horizon`` and ``|A(horizon)|/horizon``."""

    rho_F: float
    rho_D: float


def realized_rates(schedule: Schedule | Iterable[Iterable[float]], horizon: float) -> RealizedRates:
    """Empirical average frequency ``N(H)/H`` and duration ratio ``|A(H)|/H`` (compare with rho_F, rho_D)."""
    sch = _coerce_schedule(schedule)
    H = _check_nonneg("horizon", horizon)
    if H <= 0.0:
        raise ValueError(f"horizon={horizon!r} must be > 0")
    return RealizedRates(sch.count(H) / H, sch.union_length(H) / H)
