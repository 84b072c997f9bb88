"""DoS attack schedules (paper, Section II.C).

A DoS schedule is a collection of closed intervals ``[a_i, a_i + tau_i]`` with
launching times ``a_i >= 0`` and lengths ``tau_i >= 0`` (``tau_i = 0`` is an
impulsive attack).  The paper defines

* ``A(t) = union_i [a_i, a_i + tau_i] ∩ [0, t]`` and its Lebesgue measure
  ``|A(t)|`` (used in Assumption 4, DoS duration);
* ``N(t)`` = number of attacks whose start ``a_i`` lies in ``[0, t]`` (used in
  Assumption 3, DoS frequency).

With periodic sampling ``t_k = k T`` the packet sent at ``t_k`` is lost iff
``t_k`` lies in some attack interval; ``theta_k = 1`` marks that loss.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any, overload

import numpy as np

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["Schedule", "sample_eps"]

#: Relative tolerance used for sampling instants: ``eps = SAMPLE_REL_EPS * T``.
SAMPLE_REL_EPS = 1e-9
#: Relative tolerance used by :meth:`Schedule.theta` when no ``eps`` is given:
#: ``eps = THETA_REL_EPS * max(1, |t|)`` (absorbs the rounding of ``k * T``).
THETA_REL_EPS = 1e-12


def sample_eps(T: float) -> float:
    """Membership tolerance for the sampling instants ``t_k = k T``.

    ``k * T`` is computed in floating point (``15 * 0.1 == 1.5000000000000002``),
    so a sample counts as attacked when ``a_i - eps <= t_k <= a_i + tau_i + eps``
    with ``eps = 1e-9 * T``.
    """
    return SAMPLE_REL_EPS * float(T)


def _as_float(x: Any, what: str) -> float:
    if isinstance(x, (bool, np.bool_)):
        raise ValueError(f"{what} must be a real number, got bool {x!r}")
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a real number, got {x!r}") from None
    return v


@dataclass(frozen=True)
class Schedule:
    """A DoS schedule: attack intervals ``[a_i, a_i + tau_i]``.

    ``intervals`` holds the pairs ``(a_i, tau_i)`` sorted by ``a_i`` (ties by
    ``tau_i``).  Any iterable of pairs is accepted and normalised to a tuple of
    float pairs.  Overlapping intervals are kept as given: ``N(t)`` counts every
    start, while ``|A(t)|`` is the measure of their union.

    Raises ``ValueError`` if some ``a_i`` or ``tau_i`` is not finite, ``a_i < 0``
    or ``tau_i < 0``.
    """

    intervals: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        raw = self.intervals
        if isinstance(raw, np.ndarray):
            raw = raw.tolist()
        if isinstance(raw, (str, bytes)) or not isinstance(raw, Iterable):
            raise ValueError(
                f"Schedule.intervals must be a sequence of (a_i, tau_i) pairs, got {raw!r}"
            )
        out = []
        for i, pair in enumerate(raw):
            if isinstance(pair, np.ndarray):
                pair = pair.tolist()
            if isinstance(pair, (str, bytes)) or not isinstance(pair, Sequence) or len(pair) != 2:
                raise ValueError(
                    f"DoS interval {i} must be a pair (a_i, tau_i) = (start, length), got {pair!r}"
                )
            a = _as_float(pair[0], f"DoS interval {i}: start a_i")
            tau = _as_float(pair[1], f"DoS interval {i}: length tau_i")
            if not (math.isfinite(a) and math.isfinite(tau)):
                raise ValueError(
                    f"DoS interval {i}: start a_i={a!r} and length tau_i={tau!r} must be finite"
                )
            if a < 0.0:
                raise ValueError(f"DoS interval {i}: start a_i={a!r} must be >= 0")
            if tau < 0.0:
                raise ValueError(
                    f"DoS interval {i}: length tau_i={tau!r} must be >= 0 (0 = impulsive attack)"
                )
            out.append((a + 0.0, tau + 0.0))  # +0.0 turns -0.0 into 0.0
        out.sort()
        object.__setattr__(self, "intervals", tuple(out))

    # ------------------------------------------------------------------ basics
    @classmethod
    def empty(cls) -> "Schedule":
        """The schedule with no attacks."""
        return cls(())

    @classmethod
    def from_list(cls, data: Iterable[Iterable[float]]) -> Schedule:
        """Inverse of :meth:`to_list` (``[[a_i, tau_i], ...]``)."""
        return cls(tuple(tuple(p) for p in data))  # type: ignore[misc]  # __post_init__ checks the pairs

    def to_list(self) -> list[list[float]]:
        """JSON-friendly ``[[a_i, tau_i], ...]``."""
        return [[a, tau] for a, tau in self.intervals]

    def __len__(self) -> int:
        return len(self.intervals)

    @cached_property
    def starts(self) -> np.ndarray:
        """Launching times ``a_i`` (sorted), float64."""
        return np.array([a for a, _ in self.intervals], dtype=np.float64)

    @cached_property
    def lengths(self) -> np.ndarray:
        """Lengths ``tau_i`` (in the order of :attr:`starts`), float64."""
        return np.array([tau for _, tau in self.intervals], dtype=np.float64)

    @cached_property
    def ends(self) -> np.ndarray:
        """End times ``a_i + tau_i`` (in the order of :attr:`starts`), float64."""
        return self.starts + self.lengths

    @cached_property
    def merged(self) -> tuple[tuple[float, float], ...]:
        """Union of the closed attack intervals as disjoint ``(start, end)`` pairs.

        Overlapping or touching intervals are merged; impulsive attacks inside
        another interval disappear, isolated ones stay as ``(a, a)``.
        """
        out: list[list[float]] = []
        for a, e in zip(self.starts.tolist(), self.ends.tolist()):
            if out and a <= out[-1][1]:
                if e > out[-1][1]:
                    out[-1][1] = e
            else:
                out.append([a, e])
        return tuple((s, e) for s, e in out)

    @cached_property
    def _merged_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m = self.merged
        s = np.array([p[0] for p in m], dtype=np.float64)
        e = np.array([p[1] for p in m], dtype=np.float64)
        # cum[j] = total measure of merged intervals 0..j-1
        cum = np.concatenate(([0.0], np.cumsum(e - s)))
        return s, e, cum

    @property
    def total_duration(self) -> float:
        """``|A(inf)|``: measure of the union of all attack intervals."""
        return float(self._merged_arrays[2][-1])

    # ------------------------------------------------------ N(t) and |A(t)|
    @overload
    def count(self, t: float) -> int: ...
    @overload
    def count(self, t: np.ndarray) -> np.ndarray: ...
    def count(self, t: float | np.ndarray) -> int | np.ndarray:
        """``N(t)``: number of attacks with start ``a_i`` in ``[0, t]`` (Assumption 3).

        Scalar in -> int out; array in -> int64 array out.
        """
        arr = np.asarray(t, dtype=np.float64)
        n = np.searchsorted(self.starts, arr, side="right")
        n = np.where(arr < 0.0, 0, n)
        if arr.ndim == 0:
            return int(n)
        return n.astype(np.int64)

    @overload
    def union_length(self, t: float) -> float: ...
    @overload
    def union_length(self, t: np.ndarray) -> np.ndarray: ...
    def union_length(self, t: float | np.ndarray) -> float | np.ndarray:
        """``|A(t)|``: Lebesgue measure of the attacked set in ``[0, t]`` (Assumption 4).

        Exact (merged intervals, no time grid).  Scalar in -> float out, array
        in -> float64 array out.
        """
        arr = np.asarray(t, dtype=np.float64)
        s, e, cum = self._merged_arrays
        if s.size == 0:
            out = np.zeros_like(arr)
        else:
            j = np.searchsorted(s, arr, side="right") - 1  # last merged interval starting <= t
            jj = np.clip(j, 0, None)
            partial = np.clip(np.minimum(e[jj], arr) - s[jj], 0.0, None)
            out = np.where(j >= 0, cum[jj] + partial, 0.0)
        if arr.ndim == 0:
            return float(out)
        return out

    # ------------------------------------------------------------------ theta
    @overload
    def theta(self, t: float, eps: float | None = None) -> int: ...
    @overload
    def theta(self, t: np.ndarray, eps: float | None = None) -> np.ndarray: ...
    def theta(self, t: float | np.ndarray, eps: float | None = None) -> int | np.ndarray:
        """Attack indicator at time(s) ``t``: 1 iff ``t`` lies in some ``[a_i, a_i + tau_i]``.

        Membership is tested as ``a_i - eps <= t <= a_i + tau_i + eps``.  With
        ``eps=None`` a tiny relative tolerance ``1e-12 * max(1, |t|)`` absorbs
        the rounding of ``k * T``; pass ``eps=0.0`` for the exact definition or
        ``eps=sample_eps(T)`` to match :meth:`theta_samples`.

        Scalar in -> int out; array in -> uint8 array out.
        """
        arr = np.asarray(t, dtype=np.float64)
        if eps is None:
            e_tol = THETA_REL_EPS * np.maximum(1.0, np.abs(arr))
        else:
            e_tol = np.full_like(arr, float(eps))
        s, e, _ = self._merged_arrays
        if s.size == 0:
            out = np.zeros(arr.shape, dtype=np.uint8)
        else:
            # Last merged interval whose (tolerant) start is <= t.  Merged
            # intervals are disjoint, so if t is not within eps of its end it is
            # not within eps of any earlier end either.
            j = np.searchsorted(s, arr + e_tol, side="right") - 1
            jj = np.clip(j, 0, None)
            inside = (j >= 0) & (arr - e_tol <= e[jj])
            out = inside.astype(np.uint8)
        if arr.ndim == 0:
            return int(out)
        return out

    def theta_samples(self, T: float, K: int) -> np.ndarray:
        """``theta_k`` for ``t_k = k T``, ``k = 0..K-1`` (uint8 array of length ``K``).

        ``theta_k = 1`` iff the packet sent at ``t_k`` is lost, i.e.
        ``a_i - eps <= k T <= a_i + tau_i + eps`` for some ``i`` with
        ``eps = 1e-9 T`` (so ``15 * 0.1 = 1.5000000000000002`` is inside ``[1.0, 1.5]``).
        """
        T = _as_float(T, "sampling period T")
        if not (math.isfinite(T) and T > 0.0):
            raise ValueError(f"sampling period T={T!r} must be finite and > 0")
        K = int(K)
        if K < 0:
            raise ValueError(f"number of samples K={K} must be >= 0")
        t = np.arange(K, dtype=np.float64) * T
        return self.theta(t, eps=sample_eps(T))

    @classmethod
    def from_theta(cls, theta: npt.ArrayLike, T: float) -> Schedule:
        """Schedule whose samples are exactly ``theta`` (inverse of :meth:`theta_samples`).

        Each maximal run of attacked samples ``k..k+j`` becomes one attack
        ``[k T, (k + j) T]`` (``a = k T``, ``tau = j T``); a single attacked
        sample is an impulsive attack (``tau = 0``).  ``theta`` must be a 1-D
        sequence of 0/1 (or bool).

        This is the reading with the fewest attacks and the least duration
        among "one attack per run" readings, and the one the greedy attacker
        budgets with.  It is not the only schedule producing ``theta``: e.g.
        impulsive attacks at every ``t_k`` (``rho_F >= 1/T``, ``kappa_D = rho_D = 0``)
        also lose every packet, so the budget of an arbitrary schedule is not
        always met by ``from_theta(schedule.theta_samples(T, K))``.
        """
        T = _as_float(T, "sampling period T")
        if not (math.isfinite(T) and T > 0.0):
            raise ValueError(f"sampling period T={T!r} must be finite and > 0")
        th = np.asarray(theta)
        if th.ndim != 1:
            raise ValueError(f"theta must be a 1-D sequence of 0/1, got shape {th.shape}")
        if th.size and not np.all((th == 0) | (th == 1)):
            raise ValueError("theta must contain only 0 and 1")
        on = th.astype(bool)
        if not on.any():
            return cls(())
        d = np.diff(np.concatenate(([False], on, [False])).astype(np.int8))
        run_starts = np.flatnonzero(d == 1)
        run_ends = np.flatnonzero(d == -1) - 1  # last attacked sample of each run
        return cls(
            tuple(
                (float(k0) * T, float(k1 - k0) * T)
                for k0, k1 in zip(run_starts.tolist(), run_ends.tolist())
            )
        )
