"""Registry of DoS schedule generators, looked up by name.

``make_schedule(kind, params, *, T, horizon, seed=None)`` builds an offline
:class:`~attackers.schedule.Schedule`.  Kinds (see :data:`GENERATORS`):

* ``"none"``: no attacks.
* ``"intervals"``: ``intervals = [[a_i, tau_i], ...]`` given explicitly.
* ``"periodic"``: ``period``, ``length``, ``offset=0``: attacks
  ``[offset + j period, offset + j period + length]`` with start ``<= horizon``;
  it satisfies Assumption 3 with ``rho_F = 1/period`` and Assumption 4 with
  ``rho_D = length/period``.
* ``"random"``: ``kappa_F, rho_F, kappa_D, rho_D`` (+ optional ``seed``,
  ``p_impulsive``, ``gap_scale``, ``fill_min``): random attacks over
  ``[0, horizon]`` guaranteed to satisfy Assumptions 3 and 4 with these
  constants, and using a sizeable part of the budget.
* ``"greedy"``: ONLINE (state dependent), so it cannot be generated offline:
  ``make_schedule`` raises ``ValueError``; build it with :func:`make_greedy`
  and run it inside the simulator (``is_online("greedy")`` is ``True``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from .checks import RHO_D, RHO_D_WHY, field
from .schedule import Schedule

if TYPE_CHECKING:  # numba: imported only where the online attacker is built (make_greedy)
    from .greedy import GreedyAttacker

__all__ = ["GENERATORS", "ONLINE_KINDS", "PARAMS", "make_schedule", "make_greedy", "is_online"]


# ---------------------------------------------------------------- validation
def _num(kind: str, name: str, value: Any) -> float:
    return field(f"attack kind {kind!r}: parameter {name!r}", value)


def _nonneg(kind: str, name: str, value: Any) -> float:
    return field(f"attack kind {kind!r}: parameter {name!r}", value, lo=0.0)


def _rho_D(kind: str, value: Any) -> float:
    return field(f"attack kind {kind!r}: parameter 'rho_D'", value, RHO_D_WHY, **RHO_D)


def _unit(kind: str, name: str, value: Any) -> float:
    return field(f"attack kind {kind!r}: parameter {name!r}", value, lo=0.0, hi=1.0)


def _check_keys(kind: str, params: Mapping, required: tuple[str, ...], optional: tuple[str, ...]) -> None:
    unknown = sorted(set(params) - set(required) - set(optional))
    if unknown:
        allowed = ", ".join(repr(k) for k in required + optional) or "none"
        raise ValueError(
            f"attack kind {kind!r}: unknown parameter(s) {', '.join(map(repr, unknown))} "
            f"(allowed: {allowed})"
        )
    missing = [k for k in required if k not in params]
    if missing:
        raise ValueError(f"attack kind {kind!r}: missing parameter(s) {', '.join(map(repr, missing))}")


# ---------------------------------------------------------------- generators
#: Each kind's parameters, (required, optional): the one declaration the generators check and the
#: scenario reader (``testbed.scenario``) names an unknown key against.
PARAMS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "none": ((), ()),
    "intervals": (("intervals",), ()),
    "periodic": (("period", "length"), ("offset",)),
    "random": (("kappa_F", "rho_F", "kappa_D", "rho_D"), ("seed", "p_impulsive", "gap_scale", "fill_min")),
    "greedy": (("kappa_F", "rho_F", "kappa_D", "rho_D"), ("threshold",)),
    "trace": (("samples", "T", "n_samples"), ("source",)),
}

#: Safety cap on the number of attacks the random generator produces.
_MAX_RANDOM_ATTACKS = 10_000_000

def gen_none(params: Mapping, *, T: float, horizon: float, rng: np.random.Generator) -> Schedule:
    """No DoS attack: ``N(t) = |A(t)| = 0``."""
    _check_keys("none", params, *PARAMS["none"])
    return Schedule(())


def gen_intervals(params: Mapping, *, T: float, horizon: float, rng: np.random.Generator) -> Schedule:
    """Explicit attacks ``intervals = [[a_i, tau_i], ...]`` (start, length)."""
    kind = "intervals"
    _check_keys(kind, params, *PARAMS[kind])
    raw = params["intervals"]
    if isinstance(raw, (str, bytes, Mapping)):
        raise ValueError(f"attack kind {kind!r}: parameter 'intervals' must be a list of [start, length] pairs")
    try:
        items = list(raw)
    except TypeError:
        raise ValueError(
            f"attack kind {kind!r}: parameter 'intervals' must be a list of [start, length] pairs, got {raw!r}"
        ) from None
    pairs = []
    for i, p in enumerate(items):
        if isinstance(p, (str, bytes)) or not hasattr(p, "__len__") or len(p) != 2:
            raise ValueError(
                f"attack kind {kind!r}: intervals[{i}]={p!r} must be a pair [start, length]"
            )
        a = _nonneg(kind, f"intervals[{i}][0] (start a_i)", p[0])
        tau = _nonneg(kind, f"intervals[{i}][1] (length tau_i)", p[1])
        pairs.append((a, tau))
    return Schedule(tuple(pairs))


def gen_periodic(params: Mapping, *, T: float, horizon: float, rng: np.random.Generator) -> Schedule:
    """Periodic attacks ``[offset + j period, offset + j period + length]``, start ``<= horizon``.

    Requires ``period > 0``, ``0 <= length < period``, ``offset >= 0``.  Satisfies
    Assumption 3 with ``rho_F = 1/period`` (``kappa_F = 1``) and Assumption 4 with
    ``rho_D = length/period`` (``kappa_D = length``).
    """
    kind = "periodic"
    _check_keys(kind, params, *PARAMS[kind])
    period = _num(kind, "period", params["period"])
    length = _nonneg(kind, "length", params["length"])
    offset = _nonneg(kind, "offset", params.get("offset", 0.0))
    if period <= 0.0:
        raise ValueError(f"attack kind {kind!r}: parameter 'period'={params['period']!r} must be > 0")
    if not length < period:
        raise ValueError(
            f"attack kind {kind!r}: parameter 'length'={params['length']!r} must be < period={period!r} "
            "(otherwise the channel is always jammed and rho_D >= 1)"
        )
    if offset > horizon:
        return Schedule(())
    n = int(math.floor((horizon - offset) / period)) + 1
    starts = offset + np.arange(n + 1, dtype=np.float64) * period
    starts = starts[starts <= horizon]
    return Schedule(tuple((float(a), length) for a in starts))


def gen_random(params: Mapping, *, T: float, horizon: float, rng: np.random.Generator) -> Schedule:
    """Random attacks over ``[0, horizon]`` that satisfy Assumptions 3 and 4 by construction.

    Parameters (in ``params``): ``kappa_F >= 0``, ``rho_F >= 0`` (Assumption 3),
    ``kappa_D >= 0``, ``rho_D in [0, 1)`` (Assumption 4); optional
    ``p_impulsive`` (probability of an impulsive attack, default 0.2),
    ``gap_scale`` (mean extra waiting time after the earliest admissible start,
    in units of ``(1 - rho_D)/rho_F``, the mean idle time per attack when both
    budgets are used; default 0.5), ``fill_min`` (lower end of the
    uniformly drawn fraction of the available duration budget each
    non-impulsive attack uses; default 0.3).

    Construction: attacks are placed one after another, disjoint.  The next
    start ``a`` is the earliest time that is after the previous attack's end
    and satisfies ``N + 1 <= kappa_F + rho_F a`` (Assumption 3 at the new start),
    plus (with probability 3/4) a random exponential delay.  Its length is a
    ``min(u tau_max, cap)`` with a random fraction ``u ~ U(fill_min, 1)``, where
    ``tau_max = (kappa_D + rho_D a - A_before) / (1 - rho_D)`` is the largest
    length keeping ``A_before + tau <= kappa_D + rho_D (a + tau)`` (Assumption 4
    at the new end, where ``|A(t)| - rho_D t`` peaks) and ``cap`` paces the
    lengths with the frequency budget (up to the next admissible start, at
    least ``0.5/rho_F``).  Unused budget carries over, so over long horizons the
    realized rates are a large fraction of ``rho_F`` and ``rho_D`` (typically
    well above one half).  Both inequalities are enforced with a
    small floating-point safety margin, so :func:`attackers.budget.check` gives
    ``kappa_F_min <= kappa_F`` and ``kappa_D_min <= kappa_D``.  Intervals are
    clipped to end by ``horizon``.
    """
    kind = "random"
    _check_keys(kind, params, *PARAMS[kind])
    kappa_F = _nonneg(kind, "kappa_F", params["kappa_F"])
    rho_F = _nonneg(kind, "rho_F", params["rho_F"])
    kappa_D = _nonneg(kind, "kappa_D", params["kappa_D"])
    rho_D = _rho_D(kind, params["rho_D"])
    p_imp = _unit(kind, "p_impulsive", params.get("p_impulsive", 0.2))
    gap_scale = _nonneg(kind, "gap_scale", params.get("gap_scale", 0.5))
    fill_min = _unit(kind, "fill_min", params.get("fill_min", 0.3))

    H = float(horizon)
    # Mean extra delay between attacks.
    if rho_F > 0.0:
        # idle time per attack is (1 - rho_D)/rho_F when both budgets are used
        mean_gap = gap_scale * (1.0 - rho_D) / rho_F
    else:
        # only floor(kappa_F) attacks ever: spread them over the horizon
        mean_gap = gap_scale * H / (math.floor(kappa_F) + 1.0)

    starts: list[float] = []
    lengths: list[float] = []
    n = 0  # N before the next attack
    A = 0.0  # |A| before the next attack (attacks are disjoint)
    t_free = 0.0  # the next attack must start after this time
    while True:
        # Assumption 3 at the new start: n + 1 <= kappa_F + rho_F a.
        need = n + 1.0 - kappa_F
        if need <= 0.0:
            a_F = 0.0
        elif rho_F > 0.0:
            a_F = need / rho_F
            while (n + 1.0) - rho_F * a_F > kappa_F:  # exact w.r.t. the checker's arithmetic
                a_F = math.nextafter(a_F, math.inf)
        else:
            break
        a = max(a_F, t_free)
        if mean_gap > 0.0 and rng.random() >= 0.25:  # sometimes start as early as allowed
            a += float(rng.exponential(mean_gap))
        if a > H:
            break
        # Assumption 4 at the new end: A + tau <= kappa_D + rho_D (a + tau).
        slack = kappa_D + rho_D * a - A
        margin = 1e-10 * max(1.0, kappa_D + rho_D * H)
        tau_max = max(0.0, (slack - margin) / (1.0 - rho_D))
        # Pace the lengths with the frequency budget so that saved-up duration
        # budget is not burnt in one huge attack: at most until the next
        # admissible start (at least half a slot 1/rho_F), or a fair share of
        # the remaining horizon when rho_F = 0 (finitely many attacks).
        if rho_F > 0.0:
            cap = max((n + 2.0 - kappa_F) / rho_F - a, 0.5 / rho_F)
        else:
            cap = (H - a) / max(1.0, math.floor(kappa_F) - n)
        if rng.random() < p_imp or tau_max <= 0.0:
            tau = 0.0
        else:
            tau = min(tau_max * float(rng.uniform(fill_min, 1.0)), cap)
        tau = min(tau, H - a)
        starts.append(a)
        lengths.append(tau)
        n += 1
        if n > _MAX_RANDOM_ATTACKS:
            raise ValueError(
                f"attack kind {kind!r}: more than {_MAX_RANDOM_ATTACKS} attacks over horizon={H!r}; "
                "reduce kappa_F, rho_F or the horizon"
            )
        A += tau
        # Leave a strictly positive gap so consecutive attacks stay distinct.
        t_free = math.nextafter(a + tau, math.inf)
    return Schedule(tuple(zip(starts, lengths)))


def gen_greedy(params: Mapping, *, T: float, horizon: float, rng: np.random.Generator) -> Schedule:
    """The greedy attacker is ONLINE: always raises ``ValueError`` (use :func:`make_greedy`)."""
    raise ValueError(
        "attack kind 'greedy' is online (state dependent: it reacts to the plant's state); "
        "it cannot be generated as an offline schedule. Build it with "
        "attackers.make_greedy(params, T=...) / GreedyAttacker and run it inside the simulator."
    )


def gen_trace(params: Mapping, *, T: float, horizon: float, rng: np.random.Generator) -> Schedule:
    """The samples another run's attacker dropped: ``samples`` (sample indices), ``T`` (the trace's
    period) and ``n_samples`` (its length); ``source`` names where it came from.  The trace must
    have the run's T and cover the run (``n_samples * T >= horizon``)."""
    kind = "trace"
    _check_keys(kind, params, *PARAMS[kind])
    Tt = _num(kind, "T", params["T"])
    n = int(_nonneg(kind, "n_samples", params["n_samples"]))
    src = params.get("source") or "the trace"
    if abs(Tt - T) > 1e-9 * max(abs(T), 1.0):
        raise ValueError(f"attack kind 'trace': {src} was taken at T = {Tt:g} s, the run's T is {T:g} s")
    N = int(round(horizon / T))
    if n < N:
        raise ValueError(f"attack kind 'trace': {src} has {n} samples, shorter than the run ({N} samples)")
    theta = np.zeros(N, dtype=np.uint8)  # the run's length, never the trace's declared one
    for k in params["samples"]:
        k = int(k)
        if not 0 <= k < n:
            raise ValueError(f"attack kind 'trace': sample index {k} outside 0..{n - 1} in {src}")
        if k < N:
            theta[k] = 1
    return Schedule.from_theta(theta, T)


#: Generator functions by name: ``fn(params, *, T, horizon, rng) -> Schedule``.
GENERATORS: dict[str, Callable[..., Schedule]] = {
    "none": gen_none,
    "intervals": gen_intervals,
    "periodic": gen_periodic,
    "random": gen_random,
    "greedy": gen_greedy,
    "trace": gen_trace,
}

#: Kinds that depend on the closed-loop state and must run inside the simulator.
ONLINE_KINDS = frozenset({"greedy"})


def is_online(kind: str) -> bool:
    """Whether ``kind`` is an online (state dependent) attacker; ``ValueError`` if unknown."""
    _check_kind(kind)
    return kind in ONLINE_KINDS


def _check_kind(kind: object) -> None:
    if kind not in GENERATORS:
        raise ValueError(
            f"unknown attack kind {kind!r} (known kinds: {', '.join(sorted(GENERATORS))})"
        )


def _check_params(kind: str, params: Mapping | None) -> Mapping:
    if params is None:
        return {}
    if not isinstance(params, Mapping):
        raise ValueError(f"attack kind {kind!r}: params must be a dict, got {type(params).__name__}")
    return params


def make_schedule(kind: str, params: Mapping | None, *, T: float, horizon: float,
                  seed: int | np.random.SeedSequence | np.random.Generator | None = None) -> Schedule:
    """Build the offline DoS schedule ``kind`` with ``params`` over ``[0, horizon]``.

    ``T`` is the sampling period (``T > 0``), ``horizon >= 0``.  ``seed`` (int,
    ``numpy.random.SeedSequence`` or ``numpy.random.Generator``) is used by
    random kinds; it may alternatively be given as ``params["seed"]`` (giving
    both is an error).  Raises ``ValueError`` naming the unknown kind, an
    unknown/missing parameter or a bad value; for the online kind
    ``"greedy"`` (see :func:`is_online`) it raises ``ValueError`` too.
    """
    _check_kind(kind)
    params = _check_params(kind, params)
    Tf = _num(kind, "T", T)
    if Tf <= 0.0:
        raise ValueError(f"attack kind {kind!r}: sampling period T={T!r} must be > 0")
    H = _nonneg(kind, "horizon", horizon)
    p_seed = params.get("seed")
    if seed is not None and p_seed is not None:
        raise ValueError(
            f"attack kind {kind!r}: seed given twice (params['seed']={p_seed!r} and seed={seed!r})"
        )
    s = seed if seed is not None else p_seed
    if isinstance(s, (bool, np.bool_, float)) or (
        s is not None and not isinstance(s, (int, np.integer, np.random.SeedSequence, np.random.Generator))
    ):
        raise ValueError(f"attack kind {kind!r}: seed must be an int or a numpy Generator, got {s!r}")
    if isinstance(s, (int, np.integer)) and s < 0:
        raise ValueError(f"attack kind {kind!r}: seed={s!r} must be >= 0")
    rng = np.random.default_rng(s)
    return GENERATORS[kind](params, T=Tf, horizon=H, rng=rng)


def make_greedy(params: Mapping | None, *, T: float) -> GreedyAttacker:
    """Build the online greedy attacker from scenario params.

    ``params``: ``kappa_F, rho_F, kappa_D, rho_D`` (required) and ``threshold``
    (optional, default 0).  Raises ``ValueError`` on unknown/missing/bad values.
    """
    kind = "greedy"
    params = _check_params(kind, params)
    _check_keys(kind, params, *PARAMS[kind])
    vals = [_nonneg(kind, k, params[k]) for k in ("kappa_F", "rho_F", "kappa_D")]
    rho_D = _rho_D(kind, params["rho_D"])
    threshold = _unit(kind, "threshold", params.get("threshold", 0.0))
    Tf = _num(kind, "T", T)
    if Tf <= 0.0:
        raise ValueError(f"attack kind {kind!r}: sampling period T={T!r} must be > 0")
    from .greedy import GreedyAttacker

    return GreedyAttacker(vals[0], vals[1], vals[2], rho_D, Tf, threshold=threshold)
