"""DoS attackers for the testbed (paper Section II.C, Assumptions 3 and 4).

* :class:`Schedule`: attack intervals ``[a_i, a_i + tau_i]``, ``N(t)``, ``|A(t)|``,
  sampled ``theta_k`` at ``t_k = k T``.
* :func:`check` / :func:`satisfies` / :func:`realized_rates`: exact budget checker
  for Assumption 3 (``N(t) <= kappa_F + rho_F t``) and Assumption 4
  (``|A(t)| <= kappa_D + rho_D t``).
* :func:`make_schedule` / :data:`GENERATORS`: offline generators by name
  (``none``, ``intervals``, ``periodic``, ``random``); ``greedy`` is online.
* :func:`greedy_step` (numba) / :class:`GreedyAttacker`: greedy worst-case online attacker.
* :class:`Gate`: forward-or-drop decision for a live proxy.

This package depends only on numpy and numba; it never imports ``testbed`` or ``plants``.
"""

from typing import Any as _Any

from .budget import BudgetReport, RealizedRates, check, realized_rates, satisfies
from .gate import Gate
from .generators import GENERATORS, ONLINE_KINDS, is_online, make_greedy, make_schedule
from .schedule import Schedule, sample_eps

#: the greedy attacker's names, imported on first use (``attackers.greedy`` needs numba; the
#: offline schedules do not)
_GREEDY = ("GREEDY_PARAMS_SIZE", "GREEDY_STATE_SIZE", "GreedyAttacker", "greedy_init", "greedy_params",
           "greedy_run", "greedy_step")


def __getattr__(name: str) -> _Any:
    if name in _GREEDY:
        from . import greedy

        return getattr(greedy, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Schedule",
    "sample_eps",
    "BudgetReport",
    "RealizedRates",
    "check",
    "satisfies",
    "realized_rates",
    "GENERATORS",
    "ONLINE_KINDS",
    "is_online",
    "make_schedule",
    "make_greedy",
    "GREEDY_STATE_SIZE",
    "GREEDY_PARAMS_SIZE",
    "greedy_init",
    "greedy_params",
    "greedy_step",
    "greedy_run",
    "GreedyAttacker",
    "Gate",
]
