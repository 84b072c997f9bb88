"""Greedy worst-case ONLINE DoS attacker within the averagely constrained class.

The decision logic is a pure, ``numba.njit`` step function :func:`greedy_step`
acting on a float64 state vector, so the same code serves a numba batch
simulator (call it inside a jitted loop) and a live Python process (through
:class:`GreedyAttacker`).

Budget accounting uses the interval semantics of :meth:`Schedule.from_theta`:
attacking the consecutive samples ``k0..k1`` is ONE attack ``[k0 T, k1 T]``
(one start for ``N``, duration ``(k1 - k0) T`` for ``|A|``).  Hence

* starting an attack at ``t_k = k T`` needs ``N + 1 <= kappa_F + rho_F k T``
  (Assumption 3 checked at the new start), and
* attacking sample ``k`` of an attack started at ``k0`` needs
  ``D_before + (k - k0) T <= kappa_D + rho_D k T`` where ``D_before`` is the
  total length of the earlier attacks (Assumption 4 checked at the new end;
  ``|A(t)| - rho_D t`` is maximal at attack ends because ``rho_D < 1``).

Because a run of attacked samples is one interval, an attack that has to stop
at ``k`` leaves sample ``k`` un-attacked (starting a fresh attack at ``k`` would
merge with the previous run into one over-long interval).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .checks import RHO_D, RHO_D_WHY, field

__all__ = [
    "GREEDY_STATE_SIZE",
    "GREEDY_PARAMS_SIZE",
    "S_N",
    "S_D",
    "S_K0",
    "S_ON",
    "S_BEST",
    "S_LAST_K",
    "greedy_init",
    "greedy_step",
    "greedy_run",
    "greedy_params",
    "GreedyAttacker",
]

# State layout (float64 vector).
S_N = 0  #: number of attacks started so far, N
S_D = 1  #: total duration of the finished attacks (D before the current one)
S_K0 = 2  #: sample index k0 where the current attack started, or -1
S_ON = 3  #: 1.0 if the last processed sample was attacked, else 0.0
S_BEST = 4  #: largest score seen so far
S_LAST_K = 5  #: last processed sample index, -1 initially
GREEDY_STATE_SIZE = 6

# Params layout: [kappa_F, rho_F, kappa_D, rho_D, threshold].
GREEDY_PARAMS_SIZE = 5

#: Relative slack the attacker allows itself in the budget inequalities, so that
#: budgets that are exact multiples of T (e.g. kappa_D = 0.3, T = 0.1) are not
#: lost to rounding.  Far below the checker's default tolerance (1e-9).
_BUDGET_REL_EPS = 1e-12


def greedy_init() -> np.ndarray:
    """Fresh state for :func:`greedy_step`: no attacks yet, not attacking, best score 0."""
    s = np.zeros(GREEDY_STATE_SIZE, dtype=np.float64)
    s[S_K0] = -1.0
    s[S_BEST] = -np.inf
    s[S_LAST_K] = -1.0
    return s


def greedy_params(kappa_F: float, rho_F: float, kappa_D: float, rho_D: float, threshold: float = 0.0) -> np.ndarray:
    """Validated float64 params array ``[kappa_F, rho_F, kappa_D, rho_D, threshold]``.

    ``kappa_F, kappa_D, rho_F >= 0`` (Assumptions 3 and 4), ``rho_D in [0, 1)``
    (Assumption 4), ``threshold in [0, 1]``; raises ``ValueError`` otherwise.
    """
    vals = {name: field(f"greedy attacker: {name}", v, lo=0.0)
            for name, v in (("kappa_F", kappa_F), ("rho_F", rho_F), ("kappa_D", kappa_D))}
    vals["rho_D"] = field("greedy attacker: rho_D", rho_D, RHO_D_WHY, **RHO_D)
    vals["threshold"] = field("greedy attacker: threshold", threshold, lo=0.0, hi=1.0)
    return np.array(
        [vals["kappa_F"], vals["rho_F"], vals["kappa_D"], vals["rho_D"], vals["threshold"]],
        dtype=np.float64,
    )


@numba.njit(cache=True)
def greedy_step(state: np.ndarray, k: int, T: float, score: float, params: np.ndarray) -> int:
    """One decision of the greedy worst-case attacker; returns ``theta_k`` in {0, 1}.

    Parameters
    ----------
    state : float64[GREEDY_STATE_SIZE]
        Updated in place (see ``S_*`` indices; start from :func:`greedy_init`).
    k : int
        Sample index; must increase from call to call (a repeated ``k`` returns
        the previous decision without changing anything; a skipped sample ends
        a running attack at the last processed sample).
    T : float
        Sampling period, ``t_k = k T``.
    score : float
        How much the attacker would like to hurt now (e.g. ``||x_k||_inf`` or
        the quantizer range ``E_k``).  NaN never triggers a start.
    params : float64[5]
        ``[kappa_F, rho_F, kappa_D, rho_D, threshold]`` (see :func:`greedy_params`).

    Policy
    ------
    1. Continue: if the previous sample ``k-1`` was attacked by an attack started
       at ``k0``, keep attacking as long as Assumption 4 still holds at the new
       end, ``D_before + (k - k0) T <= kappa_D + rho_D k T``; long bursts are what
       hurts (the quantizer range ``E_k`` grows by ``Lambda`` per lost sample).
       When the duration budget is exhausted the attack ends at ``k-1`` and
       sample ``k`` is not attacked.
    2. Start: otherwise, start a new attack at ``t_k`` iff Assumption 3 allows
       one more start, ``N + 1 <= kappa_F + rho_F k T``, Assumption 4 holds at
       ``t_k`` (``D_before <= kappa_D + rho_D k T``), and the state is worth
       hitting: ``score >= threshold * max(scores seen so far, incl. this one)``
       (``threshold = 0``: attack whenever the budget allows).

    The produced theta sequence, read as intervals by ``Schedule.from_theta``,
    satisfies Assumptions 3 and 4 with the given constants (up to a relative
    rounding allowance of 1e-12).
    """
    kappa_F = params[0]
    rho_F = params[1]
    kappa_D = params[2]
    rho_D = params[3]
    threshold = params[4]
    kf = float(k)

    last_k = state[S_LAST_K]
    if kf == last_k:
        return 1 if state[S_ON] > 0.5 else 0
    if kf < last_k:
        raise ValueError("greedy_step: sample index k must increase")

    if score == score and score > state[S_BEST]:  # NaN-safe max
        state[S_BEST] = score

    t = kf * T
    if state[S_ON] > 0.5:
        k0 = state[S_K0]
        if kf == last_k + 1.0:
            # 1. continue the current attack if the duration budget allows
            rhs = kappa_D + rho_D * t
            state[S_LAST_K] = kf
            if state[S_D] + (kf - k0) * T <= rhs + _BUDGET_REL_EPS * max(1.0, rhs):
                return 1
            # budget exhausted: the attack ends at (k-1) T, sample k is spared
            state[S_D] += (last_k - k0) * T
            state[S_K0] = -1.0
            state[S_ON] = 0.0
            return 0
        # skipped samples: the attack ended at the last processed sample; k is
        # not adjacent to it, so a new attack may start below.
        state[S_D] += (last_k - k0) * T
        state[S_K0] = -1.0
        state[S_ON] = 0.0

    # 2. not attacking at k-1: start a new attack?
    rhs_F = kappa_F + rho_F * t
    rhs_D = kappa_D + rho_D * t
    can_F = state[S_N] + 1.0 <= rhs_F + _BUDGET_REL_EPS * max(1.0, rhs_F)
    can_D = state[S_D] <= rhs_D + _BUDGET_REL_EPS * max(1.0, rhs_D)
    if threshold <= 0.0:
        worth = True
    else:
        worth = score == score and score >= threshold * state[S_BEST]
    if can_F and can_D and worth:
        state[S_N] += 1.0
        state[S_K0] = kf
        state[S_ON] = 1.0
        state[S_LAST_K] = kf
        return 1
    state[S_LAST_K] = kf
    return 0


@numba.njit(cache=True)
def greedy_run(scores: np.ndarray, T: float, params: np.ndarray) -> np.ndarray:
    """Run :func:`greedy_step` on ``k = 0..len(scores)-1`` from a fresh state; returns theta (uint8).

    Open-loop helper (scores given in advance) for tests and batch studies.
    """
    state = np.zeros(GREEDY_STATE_SIZE, dtype=np.float64)
    state[S_K0] = -1.0
    state[S_BEST] = -np.inf
    state[S_LAST_K] = -1.0
    n = scores.shape[0]
    out = np.zeros(n, dtype=np.uint8)
    for k in range(n):
        out[k] = greedy_step(state, k, T, scores[k], params)
    return out


class GreedyAttacker:
    """Stateful Python wrapper around :func:`greedy_step` (one decision per sample ``k``).

    ``GreedyAttacker(kappa_F, rho_F, kappa_D, rho_D, T, threshold=0.0)``;
    :meth:`decide` returns ``theta_k`` for ``t_k = k T``.  The theta sequence it
    produces satisfies Assumptions 3 and 4 with ``(kappa_F, rho_F)`` and
    ``(kappa_D, rho_D)``.
    """

    def __init__(self, kappa_F: float, rho_F: float, kappa_D: float, rho_D: float, T: float,
                 threshold: float = 0.0) -> None:
        self._params = greedy_params(kappa_F, rho_F, kappa_D, rho_D, threshold)
        if isinstance(T, (bool, np.bool_)):
            raise ValueError(f"greedy attacker: sampling period T must be a real number, got {T!r}")
        try:
            Tf = float(T)
        except (TypeError, ValueError):
            raise ValueError(f"greedy attacker: sampling period T must be a real number, got {T!r}") from None
        if not (math.isfinite(Tf) and Tf > 0.0):
            raise ValueError(f"greedy attacker: sampling period T={T!r} must be finite and > 0")
        self.T = Tf
        self.state = greedy_init()

    @property
    def params(self) -> np.ndarray:
        """``[kappa_F, rho_F, kappa_D, rho_D, threshold]`` as float64 (a copy)."""
        return self._params.copy()

    kappa_F = property(lambda self: float(self._params[0]))
    rho_F = property(lambda self: float(self._params[1]))
    kappa_D = property(lambda self: float(self._params[2]))
    rho_D = property(lambda self: float(self._params[3]))
    threshold = property(lambda self: float(self._params[4]))

    def decide(self, k: int, score: float = 0.0) -> int:
        """``theta_k`` in {0, 1} for sample ``k`` (state updated); see :func:`greedy_step`."""
        return int(greedy_step(self.state, int(k), self.T, float(score), self._params))

    def reset(self) -> None:
        """Forget all history (fresh budget)."""
        self.state = greedy_init()

    @property
    def n_attacks(self) -> int:
        """``N``: attacks started so far."""
        return int(self.state[S_N])

    @property
    def attacking(self) -> bool:
        """Whether the last processed sample was attacked."""
        return bool(self.state[S_ON] > 0.5)

    def __repr__(self) -> str:
        p = self._params
        return (
            f"GreedyAttacker(kappa_F={p[0]!r}, rho_F={p[1]!r}, kappa_D={p[2]!r}, "
            f"rho_D={p[3]!r}, T={self.T!r}, threshold={p[4]!r})"
        )
